#include <arucotag/draw.hpp>

#include <algorithm>
#include <array>
#include <cmath>
#include <cstdio>
#include <limits>
#include <numeric>
#include <string>
#include <utility>

#include <opencv2/imgproc.hpp>

namespace arucotag {
namespace {

constexpr int kFont = cv::FONT_HERSHEY_SIMPLEX;

/// Stroke and text sizes for one image size: they grow with the shorter side so the overlay reads
/// the same from VGA to 4K once scaled to a screen, with a floor that stays legible on small frames.
struct Style {
  int stroke;          // outline thickness (px)
  int corner_half;     // half side of the corner-0 square (px)
  double font_scale;   // cv::putText scale
  int text_thickness;  // cv::putText thickness (px)
  int padding;         // dark box margin around the text (px)
  int gap;             // clearance between a tag (with its corner square) and a label or between labels (px)
};

Style StyleFor(cv::Size size) {
  const int shorter = std::min(size.width, size.height);
  const double scale = shorter / 480.0;
  Style style;
  style.stroke = std::max(1, shorter / 360);
  style.corner_half = 2 + style.stroke;
  // Hershey simplex below 0.45 (about 9 px digits) stops being readable.
  style.font_scale = std::max(0.45, 0.5 * scale);
  style.text_thickness = std::max(1, cvRound(1.5 * style.font_scale));
  style.padding = std::max(2, cvRound(3.0 * scale));
  style.gap = std::max(3, cvRound(2.0 * scale));
  return style;
}

std::string LabelText(const ArucoTag& tag) {
  std::string text = "id " + std::to_string(tag.id);
  if (tag.HasPose() && std::isfinite(tag.distance)) {
    char buffer[32];
    std::snprintf(buffer, sizeof(buffer), " %.2fm", tag.distance);
    text += buffer;
  }
  return text;
}

cv::Point2f Centre(const cv::Rect& r) { return {r.x + 0.5f * r.width, r.y + 0.5f * r.height}; }

double Distance(const cv::Rect& a, const cv::Rect& b) { return cv::norm(Centre(a) - Centre(b)); }

/// Nearest point to p on the closed polyline through the quad's corners.
cv::Point2f NearestOnOutline(const std::array<cv::Point2f, 4>& quad, cv::Point2f p) {
  cv::Point2f best = quad[0];
  double best_d2 = std::numeric_limits<double>::infinity();
  for (int i = 0; i < 4; ++i) {
    const cv::Point2f a = quad[i], ab = quad[(i + 1) % 4] - quad[i];
    const double len2 = ab.dot(ab);
    const double t = len2 > 0.0 ? std::clamp((p - a).dot(ab) / len2, 0.0, 1.0) : 0.0;
    const cv::Point2f q = a + ab * static_cast<float>(t);
    const double d2 = (p - q).dot(p - q);
    if (d2 < best_d2) best_d2 = d2, best = q;
  }
  return best;
}

/// Nearest point of the rectangle's pixels to p: on its border when p lies outside.
cv::Point2f NearestOnRect(const cv::Rect& r, cv::Point2f p) {
  return {std::clamp(p.x, float(r.x), float(r.x + r.width - 1)), std::clamp(p.y, float(r.y), float(r.y + r.height - 1))};
}

bool SegmentHitsRect(const cv::Rect& r, cv::Point2f a, cv::Point2f b) {
  cv::Point pa(cvRound(a.x), cvRound(a.y)), pb(cvRound(b.x), cvRound(b.y));
  return cv::clipLine(r, pa, pb);
}

/// One tag as an obstacle for labels: its convex hull grown by the corner square and outline.
struct Obstacle {
  std::vector<cv::Point2f> hull;
  cv::Rect bounds;
};

Obstacle MakeObstacle(const ArucoTag& tag, float grow) {
  std::vector<cv::Point2f> corners(tag.corners.begin(), tag.corners.end());
  const cv::Point2f centre = std::accumulate(corners.begin(), corners.end(), cv::Point2f()) * 0.25f;
  for (auto& c : corners) {
    const cv::Point2f d = c - centre;
    const float n = std::hypot(d.x, d.y);
    // sqrt(2) * grow along the diagonal moves a square's sides out by grow.
    c += n > 0.0f ? d * (std::sqrt(2.0f) * grow / n) : cv::Point2f(grow, grow);
  }
  Obstacle o;
  cv::convexHull(corners, o.hull);
  o.bounds = cv::boundingRect(o.hull);
  return o;
}

double OverlapArea(const cv::Rect& r, const Obstacle& o) {
  if ((r & o.bounds).empty()) return 0.0;
  const std::vector<cv::Point2f> rect = {cv::Point2f(r.x, r.y), cv::Point2f(r.x + r.width, r.y),
                                         cv::Point2f(r.x + r.width, r.y + r.height), cv::Point2f(r.x, r.y + r.height)};
  std::vector<cv::Point2f> inter;
  return std::max(0.0f, cv::intersectConvexConvex(rect, o.hull, inter, true));
}

bool SegmentsCross(cv::Point2f p, cv::Point2f q, cv::Point2f a, cv::Point2f b) {
  const auto side = [](cv::Point2f o, cv::Point2f u, cv::Point2f v) { return (u - o).cross(v - o); };
  const float d1 = side(a, b, p), d2 = side(a, b, q), d3 = side(p, q, a), d4 = side(p, q, b);
  return ((d1 > 0) != (d2 > 0)) && ((d3 > 0) != (d4 > 0));
}

bool SegmentHitsObstacle(const Obstacle& o, cv::Point2f a, cv::Point2f b) {
  if (!SegmentHitsRect(o.bounds, a, b)) return false;
  if (cv::pointPolygonTest(o.hull, a, false) > 0 || cv::pointPolygonTest(o.hull, b, false) > 0) return true;
  for (size_t i = 0; i < o.hull.size(); ++i) {
    if (SegmentsCross(a, b, o.hull[i], o.hull[(i + 1) % o.hull.size()])) return true;
  }
  return false;
}

/// One spot for a label and what it costs.
struct Candidate {
  LabelPlacement placement;
  double label_overlap = 0.0;  // px^2 shared with labels already placed (kept at 0 whenever possible)
  double cost = 0.0;           // everything else, see Evaluate
  bool operator<(const Candidate& o) const {
    return label_overlap != o.label_overlap ? label_overlap < o.label_overlap : cost < o.cost;
  }
};

/// The layout's working state: obstacles of all tags and the labels placed so far.
class Layout {
 public:
  Layout(cv::Size size, const std::vector<ArucoTag>& tags, std::vector<cv::Size> labels, const Style& style)
      : size_(size),
        tags_(tags),
        sizes_(std::move(labels)),
        style_(style),
        diagonal_(std::hypot(size.width, size.height)),
        placed_(tags.size()),
        is_placed_(tags.size(), false) {
    for (const auto& tag : tags) obstacles_.push_back(MakeObstacle(tag, float(style.corner_half)));
  }

  /// Places tag i's label at its best spot given the other labels placed so far.
  void Place(size_t i) {
    const Candidate best = Find(i);
    placed_[i] = best.placement;
    is_placed_[i] = true;
    full_ |= best.label_overlap > 0;
  }

  /// Whether some label could only be placed over another: the image has no room for all of them.
  bool Full() const { return full_; }

  /// Moves tag i's placed label to a better spot given all the others, if there is one; returns
  /// whether it moved. Greedy placement fixes the early labels before the later ones exist.
  bool Improve(size_t i) {
    const Candidate current = Evaluate(i, placed_[i].box, Preferred(i));
    const Candidate best = Find(i);
    if (!(best < current) || best.placement.box == current.placement.box) return false;
    placed_[i] = best.placement;
    return true;
  }

  const LabelPlacement& Placed(size_t i) const { return placed_[i]; }

 private:
  /// Tag i's default spot: centred just above the tag, or just below when above leaves the image.
  cv::Rect Preferred(size_t i) const {
    const cv::Rect bounds = obstacles_[i].bounds;
    const cv::Size label = sizes_[i];
    const int x = cvRound(FindTagCenter(tags_[i]).x - 0.5f * label.width);
    const int above = bounds.y - style_.gap - label.height;
    return Clamp({{x, above >= 0 ? above : bounds.y + bounds.height + style_.gap}, label});
  }

  /// Tag i's best spot given every other placed label.
  Candidate Find(size_t i) const {
    const cv::Rect bounds = obstacles_[i].bounds;
    const cv::Point2f centre = FindTagCenter(tags_[i]);
    const int g = style_.gap, w = sizes_[i].width, h = sizes_[i].height;
    const int centred_x = cvRound(centre.x - 0.5f * w);
    const cv::Rect preferred = Preferred(i);

    // Rings further and further out: above and below slid sideways by quarter labels, then the sides.
    std::vector<cv::Rect> spots = {preferred};
    for (int ring = 0; ring < 6; ++ring) {
      const int d = g + ring * (h + g);
      for (int slide = -4; slide <= 4; ++slide) {
        const int x = centred_x + slide * w / 4;
        spots.push_back(Clamp({x, bounds.y - d - h, w, h}));
        spots.push_back(Clamp({x, bounds.y + bounds.height + d, w, h}));
      }
      const int dx = g + ring * (w / 2 + g);
      for (int slide = -2; slide <= 2; ++slide) {
        const int y = cvRound(centre.y - 0.5f * h) + slide * (h + g) / 2;
        spots.push_back(Clamp({bounds.x - dx - w, y, w, h}));
        spots.push_back(Clamp({bounds.x + bounds.width + dx, y, w, h}));
      }
    }
    Candidate best = Best(i, std::move(spots), preferred);
    // Nothing near is free of other labels: the free spots anywhere in the image, or with the
    // image full, the least covered ones.
    if (best.label_overlap > 0) {
      const Candidate anywhere = Best(i, LeastCoveredSpots(i, preferred), preferred);
      if (anywhere < best) best = anywhere;
    }
    return best;
  }

  cv::Rect Clamp(cv::Rect r) const {
    r.x = std::max(0, std::min(r.x, size_.width - r.width));
    r.y = std::max(0, std::min(r.y, size_.height - r.height));
    return r & cv::Rect(cv::Point(), size_);
  }

  /// Labels as the spaced boxes other labels must keep out of.
  cv::Rect Spaced(const cv::Rect& box) const {
    const int margin = style_.gap / 2;
    return {box.x - margin, box.y - margin, box.width + 2 * margin, box.height + 2 * margin};
  }

  /// The best of `spots` for tag i. Every cost is at least the spot's distance from `preferred`, so
  /// trying spots nearest first can stop at the first spot further away than the best cost so far.
  /// No spots at all give a candidate that loses to any other.
  Candidate Best(size_t i, std::vector<cv::Rect> spots, const cv::Rect& preferred) const {
    std::stable_sort(spots.begin(), spots.end(), [&](const cv::Rect& a, const cv::Rect& b) {
      return Distance(a, preferred) < Distance(b, preferred);
    });
    Candidate best;
    best.label_overlap = std::numeric_limits<double>::infinity();
    for (const auto& spot : spots) {
      if (best.label_overlap == 0.0 && Distance(spot, preferred) > best.cost) break;
      const Candidate c = Evaluate(i, spot, preferred);
      if (c < best) best = c;
    }
    return best;
  }

  /// Spots of `label` size on a grid over the whole image that overlap the fewest placed labels'
  /// pixels (none, while the image has room), counted on an integral image of the placed labels.
  /// With the image full, only the nearest few to `preferred` of those are kept: each costs a full
  /// evaluation and they all overlap anyway.
  std::vector<cv::Rect> LeastCoveredSpots(size_t i, const cv::Rect& preferred) const {
    const cv::Size label = sizes_[i];
    cv::Mat taken(size_, CV_8U, cv::Scalar(0));
    for (size_t j = 0; j < placed_.size(); ++j) {
      if (j != i && is_placed_[j]) taken(Spaced(placed_[j].box) & cv::Rect(cv::Point(), size_)).setTo(1);
    }
    cv::Mat sum;
    cv::integral(taken, sum, CV_32S);
    const int step = std::max(2, label.height / 2);
    std::vector<cv::Rect> spots;
    int least = std::numeric_limits<int>::max();
    for (int y = 0; y + label.height <= size_.height; y += step) {
      for (int x = 0; x + label.width <= size_.width; x += step) {
        const int x1 = x + label.width, y1 = y + label.height;
        const int covered = sum.at<int>(y1, x1) - sum.at<int>(y, x1) - sum.at<int>(y1, x) + sum.at<int>(y, x);
        if (covered > least) continue;
        if (covered < least) spots.clear(), least = covered;
        spots.emplace_back(x, y, label.width, label.height);
      }
    }
    constexpr size_t kFullImageTries = 32;
    if (least > 0 && spots.size() > kFullImageTries) {
      std::nth_element(spots.begin(), spots.begin() + kFullImageTries, spots.end(),
                       [&](const cv::Rect& a, const cv::Rect& b) {
                         return Distance(a, preferred) < Distance(b, preferred);
                       });
      spots.resize(kFullImageTries);
    }
    return spots;
  }

  /// Tag i's label at `box`, with its leader when `box` is not the default spot, and its cost
  /// against the tags and every other placed label.
  Candidate Evaluate(size_t i, const cv::Rect& box, const cv::Rect& preferred) const {
    Candidate c;
    c.placement.box = box;
    c.placement.moved = box != preferred;
    if (c.placement.moved) {
      c.placement.anchor = NearestOnOutline(tags_[i].corners, Centre(box));
      c.placement.leader_end = NearestOnRect(box, c.placement.anchor);
    }
    // Labels keep a gap between them so neighbouring boxes read as two.
    const cv::Rect spaced = Spaced(box);
    const bool moved = c.placement.moved;
    const cv::Point2f a = c.placement.anchor, b = c.placement.leader_end;
    int conflicts = 0;
    for (size_t j = 0; j < placed_.size(); ++j) {
      if (j == i || !is_placed_[j]) continue;
      const LabelPlacement& p = placed_[j];
      c.label_overlap += (spaced & p.box).area();
      if (p.moved && SegmentHitsRect(box, p.anchor, p.leader_end)) ++conflicts;
      if (moved && SegmentHitsRect(p.box, a, b)) ++conflicts;
      if (moved && p.moved && SegmentsCross(a, b, p.anchor, p.leader_end)) ++conflicts;
    }
    double covered = 0.0;
    for (size_t k = 0; k < obstacles_.size(); ++k) {
      covered += OverlapArea(box, obstacles_[k]);
      if (k != i && moved && SegmentHitsObstacle(obstacles_[k], a, b)) conflicts += 4;
    }
    // A label covering any tag, or a leader over another tag, loses to every clear spot in the
    // image; a label on a leader line, a leader under another label or two leaders crossing cost
    // a quarter of the image's diagonal each; beyond that the nearest spot wins.
    const double distance = cv::norm(Centre(box) - Centre(preferred));
    c.cost = (covered > 0.0 ? diagonal_ + covered : 0.0) + 0.25 * diagonal_ * conflicts + distance;
    return c;
  }

  cv::Size size_;
  const std::vector<ArucoTag>& tags_;
  std::vector<cv::Size> sizes_;  // label boxes, padding included
  Style style_;
  double diagonal_;
  std::vector<Obstacle> obstacles_;
  std::vector<LabelPlacement> placed_;  // by tag, valid where is_placed_
  std::vector<bool> is_placed_;
  bool full_ = false;
};

// Corners past this (px, either axis) belong to no image. Refusing them keeps every coordinate the
// layout and OpenCV's drawing derive from them within int range (fuzz_core: a NaN corner rounded to
// INT_MIN overflowed the corner square's `quad[0] - half`).
constexpr float kMaxCorner = 1 << 20;

void CheckCorners(const std::vector<ArucoTag>& tags, const char* who) {
  for (const auto& tag : tags) {
    for (const auto& c : tag.corners) {
      if (!(std::abs(c.x) <= kMaxCorner && std::abs(c.y) <= kMaxCorner)) {
        throw Error(std::string(who) + ": tag " + std::to_string(tag.id) + " has a corner at (" + std::to_string(c.x) +
                    ", " + std::to_string(c.y) + "), not finite or over 2^20 px from the image");
      }
    }
  }
}

}  // namespace

std::vector<LabelPlacement> LayoutLabels(cv::Size image_size, const std::vector<ArucoTag>& tags) {
  if (image_size.width <= 0 || image_size.height <= 0) {
    throw Error("LayoutLabels: empty image size");
  }
  CheckCorners(tags, "LayoutLabels");
  const Style style = StyleFor(image_size);
  // Top to bottom, then left to right: the labels that default to the free space above the scene
  // go first, and the result does not depend on the detector's output order.
  std::vector<size_t> order(tags.size());
  std::iota(order.begin(), order.end(), size_t{0});
  std::vector<cv::Point2f> centres;
  for (const auto& tag : tags) centres.push_back(FindTagCenter(tag));
  std::stable_sort(order.begin(), order.end(), [&](size_t a, size_t b) {
    return std::make_pair(centres[a].y, centres[a].x) < std::make_pair(centres[b].y, centres[b].x);
  });

  std::vector<std::string> texts;
  std::vector<cv::Size> text_sizes, boxes;
  for (const auto& tag : tags) {
    texts.push_back(LabelText(tag));
    int baseline = 0;
    text_sizes.push_back(cv::getTextSize(texts.back(), kFont, style.font_scale, style.text_thickness, &baseline));
    // No label has descenders ("id", digits, "m"), so the box only covers the glyphs and their stroke.
    boxes.emplace_back(text_sizes.back().width + 2 * style.padding + style.text_thickness,
                       text_sizes.back().height + 2 * style.padding + style.text_thickness);
  }
  Layout layout(image_size, tags, boxes, style);
  for (size_t i : order) layout.Place(i);
  // A few passes of moving each label to its best spot among all the others: every move lowers
  // that label's cost, and the passes stop once nothing moves. A full image cannot be helped and
  // would search all of it for every label.
  for (int pass = 0; pass < 3 && !layout.Full(); ++pass) {
    bool moved = false;
    for (size_t i : order) moved |= layout.Improve(i);
    if (!moved) break;
  }
  std::vector<LabelPlacement> labels(tags.size());
  for (size_t i = 0; i < tags.size(); ++i) {
    labels[i] = layout.Placed(i);
    labels[i].text = texts[i];
    const int inset = style.padding + style.text_thickness / 2;
    labels[i].text_origin = labels[i].box.tl() + cv::Point(inset, inset + text_sizes[i].height);
  }
  return labels;
}

void DrawDetections(cv::Mat& image, const std::vector<ArucoTag>& tags) {
  if (image.empty()) {
    throw Error("DrawDetections: empty image");
  }
  if (image.depth() != CV_8U || (image.channels() != 1 && image.channels() != 3)) {
    throw Error("DrawDetections: want an 8-bit image with 1 or 3 channels (got " +
                std::to_string(image.channels()) + " channel(s) of OpenCV depth " +
                std::to_string(image.depth()) + ")");
  }
  CheckCorners(tags, "DrawDetections");
  const bool grey = image.channels() == 1;
  const cv::Scalar outline = grey ? cv::Scalar(255) : cv::Scalar(0, 255, 0);
  const cv::Scalar first_corner = grey ? cv::Scalar(0) : cv::Scalar(0, 0, 255);
  const cv::Scalar text = grey ? cv::Scalar(255) : cv::Scalar(255, 255, 0);
  const Style style = StyleFor(image.size());

  for (const auto& tag : tags) {
    std::vector<cv::Point> quad;
    for (const auto& c : tag.corners) quad.emplace_back(cvRound(c.x), cvRound(c.y));
    cv::polylines(image, quad, true, outline, style.stroke, cv::LINE_AA);
    const cv::Point half(style.corner_half, style.corner_half);
    cv::rectangle(image, quad[0] - half, quad[0] + half, first_corner, cv::FILLED);
  }
  // Labels go on top of every outline, leaders under the labels.
  const auto labels = LayoutLabels(image.size(), tags);
  const int leader = std::max(1, style.stroke / 2 + style.stroke % 2);
  for (const auto& label : labels) {
    if (!label.moved) continue;
    // A dark edge keeps the line visible on white paper as well as on black cells.
    cv::line(image, label.anchor, label.leader_end, cv::Scalar::all(0), leader + 2, cv::LINE_AA);
    cv::line(image, label.anchor, label.leader_end, text, leader, cv::LINE_AA);
    cv::circle(image, label.anchor, leader + 1, text, cv::FILLED, cv::LINE_AA);
  }
  for (const auto& label : labels) {
    // A dimmed copy of the scene behind the text: a contrasting box that still shows what it covers.
    cv::Mat behind = image(label.box);
    behind.convertTo(behind, -1, 0.25);
    cv::rectangle(image, label.box, text, 1);
    cv::putText(image, label.text, label.text_origin, kFont, style.font_scale, text, style.text_thickness, cv::LINE_AA);
  }
}

}  // namespace arucotag

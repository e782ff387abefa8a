// Candidates of the fast path. cv::aruco::detectMarkers thresholds the whole frame with three window
// sizes (3, 13 and 23 px) and traces every contour of each binary image; on a cluttered 1080p frame
// that is about 70% of its instructions (callgrind). Here each scale gets one window, and the larger
// windows run on a downscaled frame, where they cost a quarter or a sixteenth:
// - level 0 (full resolution), 7 px window: small and sharp markers down to cv::aruco's smallest,
//   searched in horizontal strips, one per core;
// - level 1 (half resolution), 11 px window (22 px of the frame): what cv::aruco's 13 and 23 px
//   windows add, i.e. blurred and low-contrast markers, and markers across a strip boundary;
// - level 2 (quarter resolution), 5 px window: large markers, cheaply enough to run on every frame
//   while tracking.
// Quads are filtered as cv::aruco's _findMarkerContours filters them and merged within each level as
// _filterTooCloseCandidates merges them. Around one marker, OpenCvQuadsNear runs cv::aruco's own
// windows, for the corners it would start refinement from. Which regions and levels a frame
// searches is fast_detect.cpp's choice.
#include "candidates.hpp"

#include <algorithm>
#include <cmath>
#include <cstring>
#include <limits>
#include <numeric>
#include <tuple>

#include <opencv2/imgproc.hpp>

#include "contours.hpp"
#include "parallel.hpp"

#if defined(ARUCOTAG_HAND_AVX2)
#include <immintrin.h>
#endif

namespace arucotag::internal {

namespace {

#if defined(ARUCOTAG_HAND_AVX2)
// Rows [range) of HalveArea's output: 32 pixels a step from two 64-pixel runs of its input rows, the
// pairs summed by one multiply-add each (bytes times 1), the rest of the row one pixel at a time.
ARUCOTAG_AVX2 void HalveRows(const cv::Mat& src, cv::Mat& dst, const cv::Range& range) {
  const __m256i ones = _mm256_set1_epi8(1), two = _mm256_set1_epi16(2);
  const int w = dst.cols;
  for (int y = range.start; y < range.end; ++y) {
    const uchar* a = src.ptr<uchar>(2 * y);
    const uchar* b = src.ptr<uchar>(2 * y + 1);
    uchar* out = dst.ptr<uchar>(y);
    int x = 0;
    for (; x + 32 <= w; x += 32) {
      const __m256i* top = reinterpret_cast<const __m256i*>(a + 2 * x);
      const __m256i* bottom = reinterpret_cast<const __m256i*>(b + 2 * x);
      const __m256i first = _mm256_add_epi16(_mm256_maddubs_epi16(_mm256_loadu_si256(top), ones),
                                             _mm256_maddubs_epi16(_mm256_loadu_si256(bottom), ones));
      const __m256i second = _mm256_add_epi16(_mm256_maddubs_epi16(_mm256_loadu_si256(top + 1), ones),
                                              _mm256_maddubs_epi16(_mm256_loadu_si256(bottom + 1), ones));
      // packus interleaves the two by 128-bit lane: 0xD8 puts the four quarters back in order.
      const __m256i packed = _mm256_packus_epi16(_mm256_srli_epi16(_mm256_add_epi16(first, two), 2),
                                                 _mm256_srli_epi16(_mm256_add_epi16(second, two), 2));
      _mm256_storeu_si256(reinterpret_cast<__m256i*>(out + x), _mm256_permute4x64_epi64(packed, 0xD8));
    }
    for (; x < w; ++x) out[x] = static_cast<uchar>((a[2 * x] + a[2 * x + 1] + b[2 * x] + b[2 * x + 1] + 2) >> 2);
  }
}
#endif

double Scale(int level) { return 1.0 / (1 << level); }

// The fast path's own search (not OpenCvQuadsNear, which stays cv::aruco's) fits a full-resolution
// contour of fewer than kSmallContourPoints points once more at this tolerance (a share of its
// length) when cv::aruco's gives no quad: the 7 px window's outline of a 12 px marker under blur and
// noise has a pixel-high step, 5-7 vertices at 0.03 (bench's distant tag36h11 set: 2 of its 11-15 px
// markers had no candidate for that alone, both found by AprilTag 3).
constexpr int kSmallContourPoints = 60;
constexpr double kSmallContourApproxRate = 0.05;
// A small full-resolution contour that neither fit makes a convex quad of may still be a marker's:
// in a dim frame (35-60 grey levels between ink and paper under the usual sensor noise) the outline
// of a 12-17 px tag36h11 marker carries pixel spurs from the noise, or runs through a gap the 7 px
// window cut in its 1.5 px border into the marker and back (bench's dim distant set: 8-11 vertices
// at cv::aruco's tolerance, 6-8 at kSmallContourApproxRate). Its convex hull drops both and is the
// marker's square again (HullQuad), fitted at kSmallContourApproxRate of the hull's own length.
// Contours up to kHullContourPoints long (the dim set's quads so found: under 100 points), twice that for
// a ring's (it runs round the border twice), get it, and only where the binary image around it looks
// like a marker (MarkerLikeBinary): it adds candidates that cost a second look each.
constexpr int kHullContourPoints = 100;
// px: and only outlines this small (bigger markers' borders are over 1.5 px wide and hold together).
constexpr int kHullMaxSide = 24;
// MarkerLikeBinary's rings, in the quad's grid (0 at its outline, 0.5 its centre): half a border cell
// inside an 8-cell marker (the dark border ring), and just outside the outline (the light quiet zone).
constexpr double kBorderRing = 0.06;
constexpr double kQuietRing = -0.08;
// Shares of foreground (dark) samples: the border ring at least, the quiet ring at most (measured on
// the dim set's hull quads on markers: border 0.78-0.84, quiet 0.12-0.22).
constexpr double kMinBorderDark = 0.6;
constexpr double kMaxQuietDark = 0.4;
// The rings a quarter and a third of the way in (the cells): not all dark, or it is a solid blob.
constexpr double kCellRings[] = {0.25, 0.35};
constexpr double kMaxCellsDark = 0.85;
// LightAround: share of light pixels just outside the contour's bounding box, at least.
constexpr double kMinLightAround = 0.7;

// Level pixel -> full-resolution pixel (pixel centres at integers: a level-l pixel covers 2^l
// full-resolution pixels).
cv::Point2f ToFull(const cv::Point2f& p, int level) {
  const float s = static_cast<float>(1 << level);
  return (p + cv::Point2f(0.5f, 0.5f)) * s - cv::Point2f(0.5f, 0.5f);
}

int MaxDim(const cv::Size& s) { return std::max(s.width, s.height); }

// cv::adaptiveThreshold(src, MEAN_C, THRESH_BINARY_INV, W, constant) written into `out`, which
// gets a 1-pixel zero frame around it (what BorderScan needs). Same decision as OpenCV: black
// (kForeground, where OpenCV writes 255) where src + floor(constant) <= round(box mean), edges
// replicated. The box sums are 16-bit, row by row, so the compiler vectorises every loop; OpenCV's
// version compares through a per-pixel table look-up.
template <int W>
ARUCOTAG_INLINE void BoxThreshold(const cv::Mat& src, int delta, cv::Mat& out) {
  constexpr int r = W / 2;
  constexpr int area = W * W;
  // 2 (src + delta) area <= 2 sum + area holds, for integers and an odd area, exactly where
  // sum > src area + delta area - (area + 1) / 2: one signed 16-bit comparison a pixel (Threshold
  // checks that both sides fit).
  const int16_t bias = static_cast<int16_t>(delta * area - (area + 1) / 2);
  const int w = src.cols, h = src.rows;
  out.create(h + 2, w + 2, CV_8UC1);
  out.row(0).setTo(0);
  out.row(h + 1).setTo(0);
  std::vector<uint16_t> cols(w + 2 * r, 0);
  uint16_t* col = cols.data() + r;
  const auto row = [&](int y) { return src.ptr<uchar>(std::min(std::max(y, 0), h - 1)); };
  for (int k = -r; k <= r; ++k) {
    const uchar* in = row(k);
    for (int x = 0; x < w; ++x) col[x] = static_cast<uint16_t>(col[x] + in[x]);
  }
  for (int y = 0; y < h; ++y) {
    if (y > 0) {
      const uchar* add = row(y + r);
      const uchar* sub = row(y - r - 1);
      for (int x = 0; x < w; ++x) col[x] = static_cast<uint16_t>(col[x] + add[x] - sub[x]);
    }
    for (int k = 1; k <= r; ++k) {
      col[-k] = col[0];
      col[w - 1 + k] = col[w - 1];
    }
    const uchar* __restrict in = src.ptr<uchar>(y);
    uchar* __restrict dst = out.ptr<uchar>(y + 1);
    dst[0] = 0;
    dst[w + 1] = 0;
    const uint16_t* __restrict c = col - r;
    for (int x = 0; x < w; ++x) {
      uint16_t sum = 0;
      for (int k = 0; k < W; ++k) sum = static_cast<uint16_t>(sum + c[x + k]);
      const int16_t limit = static_cast<int16_t>(in[x] * area + bias);
      dst[x + 1] = static_cast<int16_t>(sum) > limit ? kForeground : kBackground;
    }
  }
}

// The windows the search levels use, each built for AVX2 too (ARUCOTAG_VECTOR_CLONES).
ARUCOTAG_VECTOR_CLONES void BoxThreshold5(const cv::Mat& src, int delta, cv::Mat& out) { BoxThreshold<5>(src, delta, out); }
ARUCOTAG_VECTOR_CLONES void BoxThreshold7(const cv::Mat& src, int delta, cv::Mat& out) { BoxThreshold<7>(src, delta, out); }
ARUCOTAG_VECTOR_CLONES void BoxThreshold11(const cv::Mat& src, int delta, cv::Mat& out) { BoxThreshold<11>(src, delta, out); }

}  // namespace

void Threshold(const cv::Mat& src, int window, double constant, cv::Mat& out) {
  const int delta = cvFloor(constant);
  // 16-bit headroom: (255 + delta) * W^2 must fit an int16_t.
  const bool fits = delta >= 0 && (255 + delta) * window * window <= 32767;
  if (fits && window == 5) return BoxThreshold5(src, delta, out);
  if (fits && window == 7) return BoxThreshold7(src, delta, out);
  if (fits && window == 11) return BoxThreshold11(src, delta, out);
  cv::Mat binary;
  cv::adaptiveThreshold(src, binary, kForeground, cv::ADAPTIVE_THRESH_MEAN_C, cv::THRESH_BINARY_INV, window, constant);
  cv::copyMakeBorder(binary, out, 1, 1, 1, 1, cv::BORDER_CONSTANT, cv::Scalar(0));
}

namespace {

// Share of dark (foreground) pixels of `binary` (with its 1-pixel frame; `q` in the coordinates
// without it) at 32 points along the ring at grid offset t inside quad q (t < 0: outside).
double RingDarkShare(const cv::Mat& binary, const std::array<cv::Point2f, 4>& q, double t) {
  const cv::Point2f centre = (q[0] + q[1] + q[2] + q[3]) * 0.25f;
  const float towards = static_cast<float>(2.0 * t);  // a corner moved this share towards the centre
  std::array<cv::Point2f, 4> ring;
  for (int i = 0; i < 4; ++i) ring[i] = q[i] + (centre - q[i]) * towards;
  constexpr int kPerSide = 8;
  int dark = 0, total = 0;
  for (int e = 0; e < 4; ++e) {
    const cv::Point2f a = ring[e], d = ring[(e + 1) % 4] - ring[e];
    for (int k = 0; k < kPerSide; ++k) {
      const cv::Point2f p = a + d * ((k + 0.5f) / kPerSide);
      const int x = cvRound(p.x) + 1, y = cvRound(p.y) + 1;
      if (x < 0 || y < 0 || x >= binary.cols || y >= binary.rows) continue;
      ++total;
      dark += binary.at<uchar>(y, x) != kBackground;  // BorderScan's marks are foreground too
    }
  }
  return total > 0 ? static_cast<double>(dark) / total : 0.0;
}

// Whether `binary` looks like a marker around quad q: a dark border ring, a light ring outside it,
// and light cells inside.
bool MarkerLikeBinary(const cv::Mat& binary, const std::array<cv::Point2f, 4>& q) {
  return RingDarkShare(binary, q, kBorderRing) >= kMinBorderDark && RingDarkShare(binary, q, kQuietRing) <= kMaxQuietDark &&
         std::min(RingDarkShare(binary, q, kCellRings[0]), RingDarkShare(binary, q, kCellRings[1])) <= kMaxCellsDark;
}

// The convex hull of a contour (a closed chain of pixels) into `hull`, its vertices in order round
// it: the leftmost and rightmost pixel of each row (nothing else can be a vertex), then Andrew's
// monotone chain over them, already in row order. Linear in the contour and the box's height.
void ContourHull(const std::vector<cv::Point>& contour, const cv::Rect& box, std::vector<cv::Point>& hull) {
  thread_local std::vector<int> left, right;
  left.assign(static_cast<size_t>(box.height), std::numeric_limits<int>::max());
  right.assign(static_cast<size_t>(box.height), std::numeric_limits<int>::min());
  for (const cv::Point& p : contour) {
    const size_t row = static_cast<size_t>(p.y - box.y);
    left[row] = std::min(left[row], p.x);
    right[row] = std::max(right[row], p.x);
  }
  const auto cross = [](const cv::Point& o, const cv::Point& a, const cv::Point& b) {
    return static_cast<int64_t>(a.x - o.x) * (b.y - o.y) - static_cast<int64_t>(a.y - o.y) * (b.x - o.x);
  };
  // Two chains from the top row to the bottom one: down the left side, then up the right side.
  hull.clear();
  for (int row = 0; row < box.height; ++row) {
    if (left[row] > right[row]) continue;
    const cv::Point p(left[row], box.y + row);
    while (hull.size() >= 2 && cross(hull[hull.size() - 2], hull.back(), p) >= 0) hull.pop_back();
    hull.push_back(p);
  }
  const size_t lower = hull.size() + 1;
  for (int row = box.height - 1; row >= 0; --row) {
    if (left[row] > right[row]) continue;
    const cv::Point p(right[row], box.y + row);
    if (p == hull.back()) continue;
    while (hull.size() >= lower && cross(hull[hull.size() - 2], hull.back(), p) >= 0) hull.pop_back();
    hull.push_back(p);
  }
  if (hull.size() > 1 && hull.back() == hull.front()) hull.pop_back();
}

// Whether the pixels just outside `box` (coordinates without `binary`'s frame) are mostly light: a
// marker's quiet zone, or what it stands on, is. Cheaper than the hull, which most contours here
// (clutter) then do not get.
bool LightAround(const cv::Mat& binary, const cv::Rect& box) {
  // With the frame, the box's left column is box.x + 1: the one outside it is box.x.
  const int x0 = box.x, y0 = box.y, x1 = box.x + box.width + 1, y1 = box.y + box.height + 1;
  if (x1 >= binary.cols || y1 >= binary.rows) return false;
  int light = 0;
  const uchar *top = binary.ptr<uchar>(y0), *bottom = binary.ptr<uchar>(y1);
  for (int x = x0; x <= x1; ++x) light += (top[x] == kBackground) + (bottom[x] == kBackground);
  for (int y = y0 + 1; y < y1; ++y) {
    const uchar* row = binary.ptr<uchar>(y);
    light += (row[x0] == kBackground) + (row[x1] == kBackground);
  }
  const int total = 2 * (x1 - x0 + 1) + 2 * (y1 - y0 - 1);
  return light >= kMinLightAround * total;
}

// HullQuad: the quad of a small contour's convex hull (see kHullContourPoints) into `approx`, where
// the binary image around it looks like a marker; false otherwise (`approx` then holds whatever the
// fit left: the caller moves on to the next contour).
bool HullQuad(const std::vector<cv::Point>& contour, const cv::Rect& box, const cv::Mat& binary,
              std::vector<cv::Point>& approx) {
  thread_local std::vector<cv::Point> hull;
  ContourHull(contour, box, hull);
  if (hull.size() < 4) return false;
  cv::approxPolyDP(hull, approx, cv::arcLength(hull, true) * kSmallContourApproxRate, true);
  if (approx.size() != 4 || !cv::isContourConvex(approx)) return false;
  std::array<cv::Point2f, 4> corners;
  for (int i = 0; i < 4; ++i) corners[i] = cv::Point2f(approx[i]);
  return MarkerLikeBinary(binary, corners);
}

// The columns and rows (level pixels, inclusive) within which QuadsFromBinary keeps a quad's
// corners in `roi`: `inner` inside each edge of the region that lies within the image, and the
// border cv::aruco keeps from the image's own edges.
struct Kept {
  int left, top, right, bottom;
};
Kept KeptCorners(const cv::Rect& roi, const cv::Size& level_size, int level, int inner, const DetectorConfig& config) {
  // Image border as cv::aruco applies it.
  const int border = level == 0 ? config.min_distance_to_border
                                : std::max(1, static_cast<int>(std::ceil(config.min_distance_to_border * Scale(level))));
  return {roi.x > 0 ? roi.x + inner : border, roi.y > 0 ? roi.y + inner : border,
          roi.x + roi.width < level_size.width ? roi.x + roi.width - 1 - inner : level_size.width - 1 - border,
          roi.y + roi.height < level_size.height ? roi.y + roi.height - 1 - inner : level_size.height - 1 - border};
}

// FindQuads' `inner`: the rows and columns a threshold window of this size reaches past a region's
// edge (where the region's own threshold differs from the whole image's), and two pixels more.
int FindQuadsInner(int window) { return window / 2 + 2; }

// Quads in a thresholded region (`binary` with its 1-pixel zero frame; `roi` where it lies in its
// level), filtered exactly as cv::aruco's _findMarkerContours filters them, plus: a quad closer than
// `inner` to an edge of the region that is not the image's is dropped (that marker belongs to a
// neighbouring region, or its blob goes on outside). With `near` (level pixels), only contours
// whose bounding box is within `tolerance` of it on every side are fitted.
void QuadsFromBinary(cv::Mat& binary, const cv::Rect& roi, const cv::Size& level_size, const SearchTask& task,
                     int inner, const DetectorConfig& config, std::vector<Quad>& out, const cv::Rect* near = nullptr,
                     int tolerance = 0) {
  const auto [left, top, right, bottom] = KeptCorners(roi, level_size, task.level, inner, config);

  // Borders come in raster order; cv::findContours lists them last found first, and so does `out`
  // (of equal quads, merging keeps the one listed last).
  const size_t first = out.size();
  thread_local std::vector<cv::Point> border, contour, approx;
  thread_local std::vector<cv::Rect> quad_boxes;  // of the outer borders listed so far
  quad_boxes.clear();
  BorderScan scan(binary, border);
  while (scan.Next()) {
    // Only a border of a marker's perimeter is copied out of the scan's buffer (most are specks).
    const int n = scan.size();
    if (n < task.min_perimeter || n > task.max_perimeter) continue;
    contour.resize(static_cast<size_t>(n));
    std::memcpy(contour.data(), scan.points(), static_cast<size_t>(n) * sizeof(cv::Point));
    const Outline outline = Measure(contour);
    const cv::Rect& box = outline.box;
    // A hole whose box lies inside an earlier quad's (found first: raster order) is that quad's
    // inside, a marker's light cells or what a frame encloses, and no marker itself: markers do not
    // nest. Half the level-0 quads on 640x480 frames of 50 markers were such holes, each decoded to no
    // id (callgrind of Detect: 154.1 -> 146.0 M; bench_detect: the same markers and corners on every
    // set). A hole inside clutter that made no quad stays: one small blurred marker on the 1080p/20
    // set is read from such a hole only.
    const auto inside = [&](const cv::Rect& quad_box) { return (box & quad_box) == box; };
    if (scan.hole() && std::any_of(quad_boxes.begin(), quad_boxes.end(), inside)) continue;
    if (near) {
      const cv::Rect b = box + roi.tl();
      if (std::abs(b.x - near->x) > tolerance || std::abs(b.y - near->y) > tolerance ||
          std::abs(b.x + b.width - near->x - near->width) > tolerance ||
          std::abs(b.y + b.height - near->y - near->height) > tolerance) {
        continue;
      }
    }
    // A quad whose bounding box is this thin has a side under cv::aruco's min_corner_distance
    // anyway (and no decodable cells): skip the polygon fit for the clutter's lines and arcs.
    if (16 * std::min(box.width, box.height) < n) continue;
    // Likewise a contour enclosing almost nothing (a diagonal line, an arc) cannot be a quad with
    // sides of at least min_corner_distance: a square's area is n^2/16 to n^2/8 in chain steps. (The
    // outline of a marker whose border the threshold broke is one too: only its hull has a quad.)
    const bool encloses_little = 64 * std::abs(outline.twice_area) < static_cast<int64_t>(n) * n;
    const bool hull_allowed = !near && task.level == 0 && n < (encloses_little ? 2 : 1) * kHullContourPoints &&
                              std::max(box.width, box.height) <= kHullMaxSide &&
                              3 * std::min(box.width, box.height) >= std::max(box.width, box.height);
    if (encloses_little && !hull_allowed) continue;
    approx.clear();
    if (!encloses_little) {
      ApproximatePolygon(contour, n * config.polygonal_approx_accuracy_rate, approx);
      if (approx.size() != 4 && !near && task.level == 0 && n < kSmallContourPoints) {
        ApproximatePolygon(contour, n * std::max(config.polygonal_approx_accuracy_rate, kSmallContourApproxRate),
                           approx);
      }
    }
    if (approx.size() != 4 || !cv::isContourConvex(approx)) {
      if (!hull_allowed || !LightAround(binary, box) || !HullQuad(contour, box, binary, approx)) continue;
    }
    double min_dist_sq = 1e300;
    for (int j = 0; j < 4; ++j) {
      const cv::Point d = approx[j] - approx[(j + 1) % 4];
      min_dist_sq = std::min(min_dist_sq, double(d.x) * d.x + double(d.y) * d.y);
    }
    const double min_corner = n * config.min_corner_distance_rate;
    if (min_dist_sq < min_corner * min_corner) continue;
    bool outside = false;
    for (auto& p : approx) {
      p += roi.tl();
      outside |= p.x < left || p.y < top || p.x > right || p.y > bottom;
    }
    if (outside) continue;

    Quad quad;
    quad.level = task.level;
    quad.perimeter = static_cast<int>(std::lround(n / Scale(task.level)));
    for (int j = 0; j < 4; ++j) quad.corners[j] = ToFull(cv::Point2f(approx[j]), task.level);
    // Clockwise, as _reorderCandidatesCorners makes it.
    const cv::Point2f d1 = quad.corners[1] - quad.corners[0], d2 = quad.corners[2] - quad.corners[0];
    if (double(d1.x) * d2.y - double(d1.y) * d2.x < 0.0) std::swap(quad.corners[1], quad.corners[3]);
    quad.area = static_cast<float>(cv::contourArea(std::vector<cv::Point2f>(quad.corners.begin(), quad.corners.end())));
    quad.box = box + roi.tl();
    quad.hole = scan.hole();
    out.push_back(quad);
    if (!scan.hole()) quad_boxes.push_back(box);
  }
  std::reverse(out.begin() + first, out.end());
}

// Quads of one task: its region thresholded (the region's edges replicated, so quads within the
// window's reach of an inner edge are dropped), then QuadsFromBinary.
void FindQuads(const Pyramid& pyramid, const SearchTask& task, const DetectorConfig& config,
               std::vector<Quad>& out) {
  const cv::Mat& level_image = pyramid.images[task.level];
  const cv::Rect roi = task.roi & cv::Rect(0, 0, level_image.cols, level_image.rows);
  if (roi.width < task.window + 2 || roi.height < task.window + 2) return;
  cv::Mat binary;
  Threshold(level_image(roi), task.window, config.adaptive_thresh_constant, binary);
  QuadsFromBinary(binary, roi, level_image.size(), task, FindQuadsInner(task.window), config, out);
}

}  // namespace

// A task at `level` over `roi` (level pixels) with cv::aruco's perimeter limits (rates of the full
// frame), at reduced levels nothing below their min_side.
void HalveArea(const cv::Mat& src, cv::Mat& dst, int threads) {
  CV_Assert(src.type() == CV_8UC1);
  const cv::Size half(src.cols / 2, src.rows / 2);
#if defined(ARUCOTAG_HAND_AVX2)
  if (CpuHasAvx2() && src.cols % 2 == 0 && src.rows % 2 == 0 && !half.empty()) {
    dst.create(half, CV_8UC1);
    // Blocks of about 64k output pixels, as cv::resize splits its rows for the threads.
    ParallelFor(cv::Range(0, half.height), threads, [&](const cv::Range& range) { HalveRows(src, dst, range); },
                static_cast<double>(half.area()) / (1 << 16));
    return;
  }
#endif
  cv::resize(src, dst, half, 0, 0, cv::INTER_AREA);
}

SearchTask MakeTask(const DetectorConfig& config, const cv::Size& frame, int level, const cv::Rect& roi,
                    int window) {
  SearchTask task;
  task.level = level;
  task.window = window > 0 ? window : kLevelSearch[level].window;
  task.roi = roi;
  const double full = MaxDim(frame);
  task.min_perimeter = static_cast<int>(config.min_marker_perimeter_rate * full * Scale(level));
  task.min_perimeter = std::max(task.min_perimeter, 4 * kLevelSearch[level].min_side);
  task.max_perimeter = static_cast<int>(config.max_marker_perimeter_rate * full * Scale(level));
  return task;
}

void RunTasks(const Pyramid& pyramid, const std::vector<SearchTask>& tasks, const DetectorConfig& config,
              std::vector<Quad>& quads) {
  std::vector<std::vector<Quad>> per_task(tasks.size());
  ParallelFor(cv::Range(0, static_cast<int>(tasks.size())), config.threads, [&](const cv::Range& range) {
    for (int i = range.start; i < range.end; ++i) FindQuads(pyramid, tasks[i], config, per_task[i]);
  });
  for (auto& q : per_task) quads.insert(quads.end(), q.begin(), q.end());
}

namespace {

// CompleteSeams searches a coarse quad's neighbourhood at full resolution only while it covers at
// most 1 / kMaxSeamSearchDivisor of the strips' region.
constexpr int kMaxSeamSearchDivisor = 2;

}  // namespace

void CompleteSeams(const Pyramid& pyramid, const std::vector<SearchTask>& tasks, const DetectorConfig& config,
                   std::vector<Quad>& quads) {
  const cv::Size frame = pyramid.images[0].size();
  struct Seam {
    int above_last, below_first;  // the last row the strip above keeps, the first the strip below keeps
    cv::Rect region;              // every strip of those columns
  };
  std::vector<Seam> seams;
  for (size_t a = 0; a < tasks.size(); ++a) {
    const SearchTask& above = tasks[a];
    if (above.level != 0) continue;
    for (size_t b = 0; b < tasks.size(); ++b) {
      const SearchTask& below = tasks[b];
      if (below.level != 0 || below.roi.x != above.roi.x || below.roi.width != above.roi.width ||
          below.roi.y <= above.roi.y || below.roi.y >= above.roi.y + above.roi.height) {
        continue;
      }
      cv::Rect region = above.roi | below.roi;
      for (const SearchTask& t : tasks) {
        if (t.level == 0 && t.roi.x == above.roi.x && t.roi.width == above.roi.width) region |= t.roi;
      }
      // What FindQuads keeps of each strip (its region clipped to the frame, as it clips it).
      const cv::Rect whole(cv::Point(0, 0), frame);
      const Kept above_kept = KeptCorners(above.roi & whole, frame, 0, FindQuadsInner(above.window), config);
      const Kept below_kept = KeptCorners(below.roi & whole, frame, 0, FindQuadsInner(below.window), config);
      seams.push_back({above_kept.bottom, below_kept.top, region});
    }
  }
  if (seams.empty()) return;
  const int inner = FindQuadsInner(kLevelSearch[0].window);
  const size_t coarse_count = quads.size();
  // Biggest first: the neighbourhood of a marker's quad holds those of its cells and of its coarser
  // copies.
  std::vector<size_t> coarse_quads;
  for (size_t i = 0; i < coarse_count; ++i) {
    if (quads[i].level > 0) coarse_quads.push_back(i);
  }
  std::sort(coarse_quads.begin(), coarse_quads.end(),
            [&](size_t a, size_t b) { return quads[a].area > quads[b].area || (quads[a].area == quads[b].area && a < b); });
  std::vector<SearchTask> local;
  for (const size_t i : coarse_quads) {
    const Quad& coarse = quads[i];
    // The full-resolution quad of the same outline lies within a level pixel or so of this one.
    const int slack = (1 << coarse.level) + 2;
    const cv::Rect box = Bounds(coarse.corners);
    for (const Seam& seam : seams) {
      if (box.y + box.height - 1 + slack <= seam.above_last || box.y - slack >= seam.below_first ||
          (box & seam.region).empty()) {
        continue;
      }
      // Its neighbourhood, wide enough that the full-resolution quad's corners keep clear of the
      // window's reach from its edges, and with it the outlines around the marker (its quiet zone's),
      // which have no coarse quad of their own (clipped to the strips' region, whose edges the
      // strips share).
      const cv::Rect needed = Grow(box, slack + inner + 2, frame) & seam.region;
      if (std::any_of(local.begin(), local.end(), [&](const SearchTask& t) { return (needed & t.roi) == needed; })) {
        continue;
      }
      const cv::Rect roi = Grow(needed, std::max(box.width, box.height) / 4, frame) & seam.region;
      // A quad this big (a marker at arm's length, a door frame) is left to its coarse level: its
      // neighbourhood would cost another full-resolution pass over much of the frame.
      if (kMaxSeamSearchDivisor * static_cast<int64_t>(roi.area()) > seam.region.area()) continue;
      local.push_back(MakeTask(config, frame, 0, roi));
    }
  }
  std::vector<std::vector<Quad>> found(local.size());
  ParallelFor(cv::Range(0, static_cast<int>(local.size())), config.threads, [&](const cv::Range& range) {
    for (int k = range.start; k < range.end; ++k) FindQuads(pyramid, local[k], config, found[k]);
  });
  // What a strip keeps it found itself: only what crosses a seam further than both strips beside it
  // keep (no strip keeps those) is added.
  for (const auto& quads_of_task : found) {
    for (const Quad& q : quads_of_task) {
      const float top = std::min({q.corners[0].y, q.corners[1].y, q.corners[2].y, q.corners[3].y});
      const float bottom = std::max({q.corners[0].y, q.corners[1].y, q.corners[2].y, q.corners[3].y});
      if (std::any_of(seams.begin(), seams.end(), [&](const Seam& seam) {
            return bottom > seam.above_last && top < seam.below_first;
          })) {
        quads.push_back(q);
      }
    }
  }
  // A strip skips the holes inside the quads it made (a marker's light cells); one cut by the seam
  // made none there, and kept them: what the single search would not have listed goes.
  std::vector<cv::Rect> outer;
  for (size_t i = coarse_count; i < quads.size(); ++i) {
    if (!quads[i].hole) outer.push_back(quads[i].box);
  }
  quads.erase(std::remove_if(quads.begin(), quads.end(),
                             [&](const Quad& q) {
                               return q.level == 0 && q.hole && std::any_of(outer.begin(), outer.end(), [&](const cv::Rect& o) {
                                        return (q.box & o) == q.box;
                                      });
                             }),
              quads.end());
}

void SortQuads(std::vector<Quad>& quads) {
  // Lexicographic on (level, corners as y then x, area, perimeter, box as y, x, height, width, hole),
  // compared field by field until two differ (nearly always at the first corner). Comparing two
  // std::tuples of all sixteen fields built both tuples whole first, and the sort was 1.9 % of
  // Detect's instructions on 640x480 frames of 50 markers (callgrind, 6 frames: 103.18 -> 102.67 M; 20
  // markers 71.28 -> 71.05 M). The same order: quads equal in every field are the same quad.
  const auto before = [](const Quad& a, const Quad& b) {
    if (a.level != b.level) return a.level < b.level;
    for (int i = 0; i < 4; ++i) {
      if (a.corners[i].y < b.corners[i].y) return true;
      if (b.corners[i].y < a.corners[i].y) return false;
      if (a.corners[i].x < b.corners[i].x) return true;
      if (b.corners[i].x < a.corners[i].x) return false;
    }
    if (a.area < b.area) return true;
    if (b.area < a.area) return false;
    return std::make_tuple(a.perimeter, a.box.y, a.box.x, a.box.height, a.box.width, a.hole) <
           std::make_tuple(b.perimeter, b.box.y, b.box.x, b.box.height, b.box.width, b.hole);
  };
  std::sort(quads.begin(), quads.end(), before);
}

// Whether two quads are one candidate for cv::aruco's _filterTooCloseCandidates: their corners (in
// some cyclic order) closer, RMS, than `rate` of the smaller perimeter.
bool TooClose(const Quad& a, const Quad& b, double rate) {
  return CornersWithin(a.corners, b.corners, rate * std::min(a.perimeter, b.perimeter));
}

// cv::aruco's _filterTooCloseCandidates within each pyramid level: of quads too close to each
// other only the biggest is decoded. Quads of different levels are all kept (a coarse quad of a
// noisy marker may be the only good one); duplicates across levels are resolved after decoding.
std::vector<Quad> MergeQuads(std::vector<Quad> quads, double rate) {
  const size_t n = quads.size();
  std::vector<cv::Point2f> centre(n);
  for (size_t i = 0; i < n; ++i) {
    centre[i] = Centre(quads[i].corners);
  }
  std::vector<size_t> order(n);
  std::iota(order.begin(), order.end(), 0);
  std::sort(order.begin(), order.end(), [&](size_t a, size_t b) { return centre[a].x < centre[b].x; });
  std::vector<size_t> parent(n);
  std::iota(parent.begin(), parent.end(), 0);
  const auto root = [&](size_t i) {
    while (parent[i] != i) i = parent[i] = parent[parent[i]];
    return i;
  };
  for (size_t a = 0; a < n; ++a) {
    const size_t i = order[a];
    for (size_t b = a + 1; b < n; ++b) {
      const size_t j = order[b];
      // The centres differ by the mean corner offset, which is at most the RMS one.
      if (centre[j].x - centre[i].x > rate * quads[i].perimeter) break;
      if (quads[i].level != quads[j].level) continue;
      if (std::abs(centre[j].y - centre[i].y) > rate * std::min(quads[i].perimeter, quads[j].perimeter)) continue;
      if (TooClose(quads[i], quads[j], rate)) parent[root(i)] = root(j);
    }
  }
  std::vector<int> best(n, -1);
  for (size_t i = 0; i < n; ++i) {
    const size_t r = root(i);
    const int k = best[r];
    if (k < 0 || quads[i].area >= quads[k].area) best[r] = static_cast<int>(i);
  }
  std::vector<Quad> merged;
  for (size_t i = 0; i < n; ++i) {
    if (best[i] >= 0) merged.push_back(quads[best[i]]);
  }
  return merged;
}

namespace {

// One row of OpenCvQuadsNear's binary image: cv::adaptiveThreshold(MEAN_C, THRESH_BINARY_INV) with a
// window of `area` pixels whose sums come from an integral image's rows above (`t0`, `t1`: its left
// and right columns) and below (`b0`, `b1`) it. Vectorised (the box sums need 32 bits).
ARUCOTAG_VECTOR_CLONES void ThresholdRowFromSums(const int* __restrict t0, const int* __restrict t1,
                                                 const int* __restrict b0, const int* __restrict b1,
                                                 const uchar* __restrict in, int width, int delta, int area,
                                                 uchar* __restrict out) {
  for (int x = 0; x < width; ++x) {
    const int sum = b1[x] - b0[x] - t1[x] + t0[x];
    out[x] = (in[x] + delta) * 2 * area <= 2 * sum + area ? kForeground : kBackground;
  }
}

}  // namespace

// The quads cv::aruco's candidate search (every configured threshold window, same contour filters)
// finds around `corners` (full resolution), run on a small window around them: those whose
// bounding box matches the quad's within a few pixels, appended to `found`. Box means come from an
// integral image of the neighbourhood (frame edges replicated as cv::adaptiveThreshold does), so
// the binary image is the whole frame's there. Only a ring around the quad's outline is
// thresholded: its inside is set black, which leaves the outer contour as it is and skips tracing
// the marker's bits.
void OpenCvQuadsNear(const Pyramid& pyramid, const DetectorConfig& config, const std::array<cv::Point2f, 4>& corners,
                     std::vector<Quad>& found) {
  const cv::Mat& grey = pyramid.images[0];
  const cv::Size frame = grey.size();
  const cv::Rect whole(cv::Point(0, 0), frame);
  const cv::Rect box = Bounds(corners);
  const float side = MeanSide(corners);
  // Outlines of one marker at different windows lie within a few pixels of each other.
  const int tolerance = std::max(3, static_cast<int>(std::ceil(0.06f * side)));
  const cv::Rect roi = Grow(box, tolerance + 2, frame);
  const int reach = (config.adaptive_thresh_win_size_max | 1) / 2 + 1;
  const cv::Rect ext(roi.x - reach, roi.y - reach, roi.width + 2 * reach, roi.height + 2 * reach);
  const cv::Rect inside = ext & whole;
  thread_local cv::Mat patch, sums, binary;
  cv::copyMakeBorder(grey(inside), patch, inside.y - ext.y, ext.y + ext.height - inside.y - inside.height,
                     inside.x - ext.x, ext.x + ext.width - inside.x - inside.width, cv::BORDER_REPLICATE);
  cv::integral(patch, sums, CV_32S);

  // Per row of the region, the span deep inside the marker (its quad shrunk towards the centre).
  const cv::Point2f centre = Centre(corners);
  const float shrink = 1.0f - 2.0f * (tolerance + 2) / std::max(side, 1.0f);
  std::array<cv::Point2f, 4> core;
  for (int i = 0; i < 4; ++i) core[i] = centre + (corners[i] - centre) * shrink;
  std::vector<std::pair<int, int>> span(roi.height, {1, 0});
  if (shrink > 0.2f) {
    for (int yy = 0; yy < roi.height; ++yy) {
      float lo, hi;
      if (RowSpan(core, static_cast<float>(roi.y + yy), lo, hi)) {
        span[yy] = {static_cast<int>(std::ceil(lo)) - roi.x, static_cast<int>(std::floor(hi)) - roi.x};
      }
    }
  }

  const int delta = cvFloor(config.adaptive_thresh_constant);
  for (int window = config.adaptive_thresh_win_size_min; window <= config.adaptive_thresh_win_size_max;
       window += config.adaptive_thresh_win_size_step) {
    const int w = window | 1;  // cv::aruco makes even windows odd
    const int r = w / 2, area = w * w;
    binary.create(roi.height + 2, roi.width + 2, CV_8UC1);
    // Every pixel inside the 1-pixel frame is written below.
    binary.row(0).setTo(0);
    binary.row(roi.height + 1).setTo(0);
    for (int yy = 0; yy < roi.height; ++yy) {
      // Row yy of the region is row yy + reach of the patch; the integral has one more row/column.
      const int* top = sums.ptr<int>(yy + reach - r);
      const int* bottom = sums.ptr<int>(yy + reach + r + 1);
      const uchar* in = patch.ptr<uchar>(yy + reach) + reach;
      uchar* out = binary.ptr<uchar>(yy + 1) + 1;
      out[-1] = out[roi.width] = kBackground;
      ThresholdRowFromSums(top + reach - r, top + reach + r + 1, bottom + reach - r, bottom + reach + r + 1, in,
                           roi.width, delta, area, out);
      const auto [lo, hi] = span[yy];
      if (lo <= hi) std::fill(out + std::max(lo, 0), out + std::min(hi, roi.width - 1) + 1, kForeground);
    }
    QuadsFromBinary(binary, roi, frame, MakeTask(config, frame, 0, roi, w), 1, config, found, &box, tolerance);
  }
}

// The corners cv::aruco would start from for this marker: of the quads its candidate search finds
// there (OpenCvQuadsNear), the biggest of those that coincide with it, as _filterTooCloseCandidates
// keeps it. Corners come back in `decoded`'s order (rotation already applied); returns false when no
// configured window gives a quad there (a marker only the reduced levels see).
bool CornersAsOpenCv(const Pyramid& pyramid, const DetectorConfig& config, Quad& decoded) {
  thread_local std::vector<Quad> found;
  found.clear();
  OpenCvQuadsNear(pyramid, config, decoded.corners, found);
  const Quad* best = nullptr;
  for (const Quad& q : found) {
    if (TooClose(q, decoded, config.min_marker_distance_rate) && (!best || q.area > best->area)) best = &q;
  }
  if (!best) return false;
  int shift = 0;
  double closest = 1e300;
  for (int fc = 0; fc < 4; ++fc) {
    double d = 0.0;
    for (int c = 0; c < 4; ++c) d += cv::norm(best->corners[(c + fc) % 4] - decoded.corners[c]);
    if (d < closest) {
      closest = d;
      shift = fc;
    }
  }
  Quad exact = *best;
  for (int c = 0; c < 4; ++c) exact.corners[c] = best->corners[(c + shift) % 4];
  decoded = exact;
  return true;
}

}  // namespace arucotag::internal

// Fast path of Detect: search planning and tracking. Its steps have a file each: candidates.cpp
// (pyramid, thresholds, quads, merge), identify.cpp (codes, Identify, Decode) and refine_corner.cpp
// (RefineCorner). This file decides where a frame is searched. Without tracking, the whole frame at
// every level, level 0 in horizontal strips, one per core.
//
// With tracking, a frame is searched only around the markers of the previous frame, at level 2
// everywhere, in a band along the image edge the scene moves in from, and in one of
// `full_search_interval` rolling strips: a small marker that appears elsewhere is found within that
// many frames. A frame that does not look like the next one of the same stream (other size, other
// content, most tracked markers missing, nothing tracked) is searched whole.
#include "fast_detect.hpp"

#include "candidates.hpp"
#include "identify.hpp"

#include <algorithm>
#include <cmath>

#include <opencv2/imgproc.hpp>

namespace arucotag::internal {

namespace {

constexpr int kCoarseLevel = 2;  // searched over the whole frame on every frame, also when tracking
// Smallest side (px at level 1) from which a marker is reliably found there; level-0 strips overlap
// by enough to hold anything smaller whole.
constexpr int kReliableSideLevel1 = 12;
constexpr double kSceneChange = 12.0;  // mean |grey difference| of 1/32-scale thumbnails: another image
// Frames a marker that stopped decoding (too small, blurred, occluded for a moment) keeps its search
// region: it is found again the first frame it decodes, not when the rolling strip comes round.
constexpr int kCoastFrames = 15;

cv::Rect ToLevel(const cv::Rect& full, int level) {
  const int s = 1 << level;
  return cv::Rect(full.x / s, full.y / s, (full.x + full.width + s - 1) / s - full.x / s,
                  (full.y + full.height + s - 1) / s - full.y / s);
}

// Rows a level-0 strip reaches past its neighbour, so that every quad level 1 may miss lies wholly
// in one strip: a convex quad spans at most half its contour length (a 45-degree square a little
// less); contour lengths scale with resolution; plus 5% for pixel steps and the rows the threshold
// window reaches on each side of the cut.
int StripOverlap() {
  const double unseen_length = 4.0 * kReliableSideLevel1 * 2 * 1.05;
  return static_cast<int>(std::ceil(0.5 * unseen_length)) + 2 * (kLevelSearch[0].window / 2 + 2) + 2;
}

// Tasks searching the full-resolution rectangle `region` at levels [first, last]; level 0 split into
// `strips` overlapping horizontal strips (one per core for a whole frame).
void AddRegion(const DetectorConfig& config, const cv::Size& frame, const cv::Rect& region, int first, int last,
               int strips, std::vector<SearchTask>& tasks) {
  for (int level = first; level <= last; ++level) {
    if (level > 0) {
      tasks.push_back(MakeTask(config, frame, level, ToLevel(region, level)));
      continue;
    }
    const int overlap = StripOverlap();
    const int count = std::max(1, std::min(strips, region.height / std::max(1, 2 * overlap)));
    for (int k = 0; k < count; ++k) {
      const int top = region.y + region.height * k / count;
      const int bottom = k + 1 < count ? region.y + region.height * (k + 1) / count + overlap : region.y + region.height;
      tasks.push_back(MakeTask(config, frame, 0, cv::Rect(region.x, top, region.width, bottom - top)));
    }
  }
}

// Pixels thresholded and traced, at their level's resolution.
int Pixels(const std::vector<SearchTask>& tasks) {
  int pixels = 0;
  for (const auto& t : tasks) pixels += t.roi.area();
  return pixels;
}

std::vector<Found> Search(const Pyramid& pyramid, const std::vector<SearchTask>& tasks, const DetectorConfig& config,
                          const cv::aruco::Dictionary& dictionary, const cv::aruco::DetectorParameters& p,
                          FrameReport& report) {
  std::vector<Quad> quads;
  RunTasks(pyramid, tasks, config, quads);
  quads = MergeQuads(std::move(quads), config.min_marker_distance_rate);
  report.candidates = static_cast<int>(quads.size());
  report.searched_pixels = Pixels(tasks);
  return Decode(pyramid, quads, config, dictionary, p);
}

std::vector<Found> FullSearch(const Pyramid& pyramid, const DetectorConfig& config,
                              const cv::aruco::Dictionary& dictionary, const cv::aruco::DetectorParameters& p,
                              FrameReport& report) {
  const cv::Size frame = pyramid.images[0].size();
  std::vector<SearchTask> tasks;
  AddRegion(config, frame, cv::Rect(cv::Point(0, 0), frame), 0, kLevels - 1, std::max(1, cv::getNumThreads()), tasks);
  report.full_search = true;
  return Search(pyramid, tasks, config, dictionary, p, report);
}

cv::Mat Thumbnail(const Pyramid& pyramid) {
  cv::Mat thumb;
  const cv::Mat& coarse = pyramid.images[kLevels - 1];
  cv::resize(coarse, thumb, cv::Size(std::max(1, coarse.cols / 8), std::max(1, coarse.rows / 8)), 0, 0,
             cv::INTER_AREA);
  return thumb;
}

// Where a tracked marker should be in the next frame (constant velocity).
std::array<cv::Point2f, 4> Predict(const TrackedMarker& m) {
  std::array<cv::Point2f, 4> predicted = m.corners;
  for (auto& p : predicted) p += m.velocity;
  return predicted;
}

// Search tasks of a tracked frame (see the file comment).
std::vector<SearchTask> TrackedTasks(const DetectorConfig& config, const cv::Size& frame,
                                     const std::vector<TrackedMarker>& markers, int strip) {
  std::vector<SearchTask> tasks;
  // Around each tracked marker, at levels 0 and 1 (level 2 covers the whole frame below).
  std::vector<cv::Rect> rois;
  cv::Point2f mean_velocity(0.0f, 0.0f);
  int moving = 0;
  for (const auto& m : markers) {
    const std::array<cv::Point2f, 4> predicted = Predict(m);
    const float side = MeanSide(predicted);
    const int pad = static_cast<int>(std::ceil(0.5f * side + 2.0f * cv::norm(m.velocity) + 4.0f)) +
                    2 * (kLevelSearch[1].window / 2 + 2);
    const cv::Rect roi = Grow(Bounds(predicted), pad, frame);
    if (!roi.empty()) rois.push_back(roi);
    if (m.missed == 0) {
      mean_velocity += m.velocity;
      ++moving;
    }
  }
  if (moving > 0) mean_velocity *= 1.0f / moving;
  // Overlapping regions become their union: no pixel is thresholded twice.
  for (bool merged = true; merged;) {
    merged = false;
    for (size_t i = 0; i < rois.size() && !merged; ++i) {
      for (size_t j = i + 1; j < rois.size(); ++j) {
        if ((rois[i] & rois[j]).area() > 0) {
          rois[i] |= rois[j];
          rois.erase(rois.begin() + j);
          merged = true;
          break;
        }
      }
    }
  }
  for (const auto& roi : rois) AddRegion(config, frame, roi, 0, 1, 1, tasks);
  tasks.push_back(MakeTask(config, frame, kCoarseLevel, ToLevel(cv::Rect(cv::Point(0, 0), frame), kCoarseLevel)));

  // New markers come in from the edge the scene moves away from. The band is searched at level 1
  // as wide as the largest marker level 2 may miss, and at level 0 as wide as the largest marker
  // level 1 may miss (the strip overlap), each plus two frames of motion.
  const int motion = static_cast<int>(std::ceil(2.0 * cv::norm(mean_velocity)));
  const int wide = 2 * kLevelSearch[kCoarseLevel].min_side * (1 << kCoarseLevel) + 2 * (kLevelSearch[1].window + 4) + motion;
  const int narrow = StripOverlap() + motion;
  const cv::Rect whole(cv::Point(0, 0), frame);
  for (const auto& [width, level] : {std::pair<int, int>{narrow, 0}, std::pair<int, int>{wide, 1}}) {
    if (mean_velocity.x < -0.5f) AddRegion(config, frame, cv::Rect(frame.width - width, 0, width, frame.height) & whole, level, level, 1, tasks);
    if (mean_velocity.x > 0.5f) AddRegion(config, frame, cv::Rect(0, 0, width, frame.height) & whole, level, level, 1, tasks);
    if (mean_velocity.y < -0.5f) AddRegion(config, frame, cv::Rect(0, frame.height - width, frame.width, width) & whole, level, level, 1, tasks);
    if (mean_velocity.y > 0.5f) AddRegion(config, frame, cv::Rect(0, 0, frame.width, width) & whole, level, level, 1, tasks);
  }

  // One rolling strip of the whole search, reaching into the next by the strip overlap.
  const int n = std::max(1, config.full_search_interval);
  const int top = frame.height * strip / n;
  const int bottom = std::min(frame.height, frame.height * (strip + 1) / n + StripOverlap());
  AddRegion(config, frame, cv::Rect(0, top, frame.width, bottom - top), 0, 1, 1, tasks);
  return tasks;
}

// Pairs this frame's markers with the previous frame's by id (nearest predicted centre when an id
// repeats); previous markers not found coast on at their velocity for kCoastFrames.
std::vector<TrackedMarker> Track(const std::vector<Found>& found, const std::vector<TrackedMarker>& previous) {
  std::vector<TrackedMarker> next;
  std::vector<bool> used(previous.size(), false);
  for (const auto& f : found) {
    TrackedMarker t;
    t.id = f.id;
    t.corners = f.corners;
    const cv::Point2f c = Centre(f.corners);
    int best = -1;
    double best_dist = 0.0;
    for (size_t i = 0; i < previous.size(); ++i) {
      if (used[i] || previous[i].id != f.id) continue;
      const double d = cv::norm(Centre(previous[i].corners) + previous[i].velocity - c);
      if (best < 0 || d < best_dist) {
        best = static_cast<int>(i);
        best_dist = d;
      }
    }
    if (best >= 0 && best_dist < 2.0 * MeanSide(f.corners) + 8.0) {
      used[best] = true;
      // A coasting marker's corners were moved on each frame: this is one frame's motion.
      t.velocity = c - Centre(previous[best].corners);
    }
    next.push_back(t);
  }
  for (size_t i = 0; i < previous.size(); ++i) {
    if (used[i] || previous[i].missed >= kCoastFrames) continue;
    TrackedMarker t = previous[i];
    t.corners = Predict(t);
    t.missed += 1;
    next.push_back(t);
  }
  return next;
}

// Whether at least half the markers found in the previous frame, predicted well inside this one,
// are missing: the frame is probably not the next one of the stream (a cut, another camera, an
// unrelated image). One marker that stops decoding for a while is not a reason: it coasts, and its
// region is searched exactly as the full search would search it.
bool MostLost(const std::vector<TrackedMarker>& previous, const std::vector<Found>& found, const cv::Size& size) {
  int expected = 0, lost = 0;
  for (const auto& m : previous) {
    if (m.missed > 0) continue;
    const std::array<cv::Point2f, 4> predicted = Predict(m);
    const float margin = 0.25f * MeanSide(predicted) + 4.0f;
    const cv::Rect box = Bounds(predicted);
    const bool inside = box.x >= margin && box.y >= margin && box.x + box.width <= size.width - margin &&
                        box.y + box.height <= size.height - margin;
    if (!inside) continue;
    ++expected;
    const cv::Point2f c = Centre(predicted);
    const bool seen = std::any_of(found.begin(), found.end(), [&](const Found& f) {
      return f.id == m.id && cv::norm(Centre(f.corners) - c) < 2.0 * MeanSide(predicted) + 8.0;
    });
    lost += !seen;
  }
  return expected > 0 && 2 * lost >= expected;
}

}  // namespace

bool FastPathSupports(const DetectorConfig& config) {
  return config.fast_path && !config.detect_inverted_marker &&
         (config.corner_refinement == CornerRefinement::kSubpix || config.corner_refinement == CornerRefinement::kEdge);
}

std::vector<Found> FastDetect(const cv::Mat& grey, const DetectorConfig& config,
                              const cv::Ptr<cv::aruco::Dictionary>& dictionary,
                              const cv::aruco::DetectorParameters& parameters, TrackingState* state,
                              FrameReport* report) {
  FrameReport local;
  FrameReport& r = report ? *report : local;
  r = FrameReport();
  Pyramid pyramid;
  pyramid.Build(grey);

  const bool tracking = state && config.tracking;
  if (!tracking) return FullSearch(pyramid, config, *dictionary, parameters, r);

  // Copy the state out: detection runs without the lock, so one Detector serves several threads
  // (their frames then interleave, which the checks below turn into full searches).
  std::vector<TrackedMarker> previous;
  cv::Mat previous_thumb;
  bool continuing = false;
  int strip = 0;
  {
    std::lock_guard<std::mutex> lock(state->mutex);
    // Nothing tracked, nothing to gain: a frame after one without markers is searched whole, so a
    // stream without markers costs what single frames cost and a marker that appears is found at once.
    continuing = state->size == grey.size() && state->frames > 0 &&
                 std::any_of(state->markers.begin(), state->markers.end(),
                             [](const TrackedMarker& m) { return m.missed == 0; });
    previous = state->markers;
    previous_thumb = state->thumbnail;
    strip = state->strip;
  }
  const cv::Mat thumb = Thumbnail(pyramid);
  continuing = continuing && previous_thumb.size() == thumb.size() &&
               cv::norm(thumb, previous_thumb, cv::NORM_L1) / thumb.total() < kSceneChange;

  std::vector<Found> found;
  bool full = !continuing;
  if (continuing) {
    found = Search(pyramid, TrackedTasks(config, grey.size(), previous, strip), config, *dictionary, parameters, r);
    full = MostLost(previous, found, grey.size());
  }
  if (full) found = FullSearch(pyramid, config, *dictionary, parameters, r);

  {
    std::lock_guard<std::mutex> lock(state->mutex);
    state->markers = Track(found, previous);
    state->size = grey.size();
    state->thumbnail = thumb;
    state->frames += 1;
    state->strip = full ? 0 : (strip + 1) % std::max(1, config.full_search_interval);
    (full ? state->full_searches : state->tracked_frames) += 1;
  }
  return found;
}

}  // namespace arucotag::internal

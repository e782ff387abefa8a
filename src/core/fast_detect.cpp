// Fast path of Detect: search planning and tracking. Its steps have a file each: candidates.cpp
// (pyramid, thresholds, quads, merge), identify.cpp (codes, Identify, Decode) and refine_corner.cpp
// (RefineCorner). This file decides where a frame is searched. Without tracking, the whole frame at
// every level, level 0 in horizontal strips, one per core.
//
// With tracking (a video stream), a marker found in the previous frame whose refinement converged is
// first read where it is predicted (constant velocity): if its id reads there, it is found without a
// search, and Detect's refinement starts from the prediction. Only the regions of markers that did
// not read (and of markers lost a few frames ago) are searched, at levels 0 and 1, plus a band along
// the image edge the scene moves in from. Every `full_search_interval` frames the whole frame is
// searched (the budget of the full scan), so a marker that appears elsewhere is found within that
// many frames; a frame is also searched whole when a marker predicted well inside it is lost (the
// marker then coasts: its region is searched every frame for a while), and when it does not look
// like the next one of the same stream (other size, other content, nothing tracked). A tracked
// frame builds no pyramid beyond the level-1 pixels of its search regions.
#include "fast_detect.hpp"

#include "candidates.hpp"
#include "identify.hpp"
#include "parallel.hpp"
#include "refine_corner.hpp"

#include <algorithm>
#include <cmath>
#include <vector>

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

// Whether a quad overlaps a marker already found (`known`): its centre inside the marker, or the
// marker's centre inside it.
bool Overlaps(const Quad& q, const std::vector<Found>& known) {
  const cv::Point2f centre = Centre(q.corners);
  const cv::Mat quad(4, 1, CV_32FC2, const_cast<cv::Point2f*>(q.corners.data()));
  for (const Found& f : known) {
    const cv::Mat outline(4, 1, CV_32FC2, const_cast<cv::Point2f*>(f.corners.data()));
    if (cv::pointPolygonTest(outline, centre, false) >= 0.0) return true;
    if (cv::pointPolygonTest(quad, Centre(f.corners), false) >= 0.0) return true;
  }
  return false;
}

// Quads of `tasks`, merged and decoded; quads on markers in `known` (found without a search) are
// not decoded again. `strips`: the tasks' level 0 is one region cut into strips (AddRegion), whose
// seams are completed (CompleteSeams). Quads are put in order of what they are before anything is
// made of them: the result does not depend on which task (thread) found what.
std::vector<Found> Search(const Pyramid& pyramid, const std::vector<SearchTask>& tasks, bool strips,
                          const DetectorConfig& config, const cv::aruco::Dictionary& dictionary,
                          const cv::aruco::DetectorParameters& p, FrameReport& report,
                          const std::vector<Found>& known = {}) {
  std::vector<Quad> quads;
  RunTasks(pyramid, tasks, config, quads);
  if (strips) CompleteSeams(pyramid, tasks, config, quads);
  SortQuads(quads);
  quads = MergeQuads(std::move(quads), config.min_marker_distance_rate);
  if (!known.empty()) {
    quads.erase(std::remove_if(quads.begin(), quads.end(), [&](const Quad& q) { return Overlaps(q, known); }),
                quads.end());
  }
  report.candidates = static_cast<int>(quads.size());
  report.searched_pixels = Pixels(tasks);
  return Decode(pyramid, quads, config, dictionary, p);
}

std::vector<Found> FullSearch(const Pyramid& pyramid, const DetectorConfig& config,
                              const cv::aruco::Dictionary& dictionary, const cv::aruco::DetectorParameters& p,
                              FrameReport& report, const std::vector<Found>& known = {}) {
  const cv::Size frame = pyramid.images[0].size();
  std::vector<SearchTask> tasks;
  AddRegion(config, frame, cv::Rect(cv::Point(0, 0), frame), 0, kLevels - 1, ThreadBudget(config.threads), tasks);
  report.full_search = true;
  return Search(pyramid, tasks, true, config, dictionary, p, report, known);
}

// A 1/32-scale copy of the frame to tell the next frame of a stream from another image: each pixel
// the mean of every fourth pixel of every fourth row of its 32x32 block (64 of them; reading them
// all would cost as much as a pyramid level).
cv::Mat Thumbnail(const cv::Mat& grey) {
  constexpr int kBlock = 32, kStep = 4;
  cv::Mat thumb(std::max(1, grey.rows / kBlock), std::max(1, grey.cols / kBlock), CV_8UC1);
  // Row by row, each block's eight reads summed at once (a whole block unless the frame is narrower
  // than one): a quarter of the instructions of a block-by-block walk, which cost a twentieth of a
  // tracked frame.
  std::vector<int> sums(static_cast<size_t>(thumb.cols));
  const int width = std::min(grey.cols, kBlock);
  for (int ty = 0; ty < thumb.rows; ++ty) {
    std::fill(sums.begin(), sums.end(), 0);
    const int y0 = ty * kBlock, y1 = std::min(grey.rows, y0 + kBlock);
    for (int y = y0; y < y1; y += kStep) {
      const uchar* row = grey.ptr<uchar>(y);
      for (int tx = 0; tx < thumb.cols; ++tx) {
        const uchar* block = row + tx * kBlock;
        int sum = 0;
        if (width == kBlock) {
          for (int x = 0; x < kBlock; x += kStep) sum += block[x];
        } else {
          for (int x = 0; x < width; x += kStep) sum += block[x];
        }
        sums[tx] += sum;
      }
    }
    const int n = ((y1 - y0 + kStep - 1) / kStep) * ((width + kStep - 1) / kStep);
    uchar* out = thumb.ptr<uchar>(ty);
    for (int tx = 0; tx < thumb.cols; ++tx) out[tx] = cv::saturate_cast<uchar>((sums[tx] + n / 2) / std::max(1, n));
  }
  return thumb;
}

// Where a tracked marker should be in the next frame (constant velocity).
std::array<cv::Point2f, 4> Predict(const TrackedMarker& m) {
  std::array<cv::Point2f, 4> predicted = m.corners;
  for (auto& p : predicted) p += m.velocity;
  return predicted;
}

// Search tasks of a tracked frame: the regions of the markers in `searched` (coasting, or not read
// where predicted) at levels 0 and 1, and the band along the edge the scene moves in from (the mean
// velocity of the markers found last frame, `previous`).
std::vector<SearchTask> TrackedTasks(const DetectorConfig& config, const cv::Size& frame,
                                     const std::vector<TrackedMarker>& previous,
                                     const std::vector<TrackedMarker>& searched) {
  std::vector<SearchTask> tasks;
  std::vector<cv::Rect> rois;
  for (const auto& m : searched) {
    const std::array<cv::Point2f, 4> predicted = Predict(m);
    const float side = MeanSide(predicted);
    const int pad = static_cast<int>(std::ceil(0.5f * side + 2.0f * cv::norm(m.velocity) + 4.0f)) +
                    2 * (kLevelSearch[1].window / 2 + 2);
    const cv::Rect roi = Grow(Bounds(predicted), pad, frame);
    if (!roi.empty()) rois.push_back(roi);
  }
  cv::Point2f mean_velocity(0.0f, 0.0f);
  int moving = 0;
  for (const auto& m : previous) {
    if (m.missed != 0) continue;
    mean_velocity += m.velocity;
    ++moving;
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

  // New markers come in from the edge the scene moves away from. The band is searched at level 1
  // as wide as the largest marker the full scan's level 2 would find, and at level 0 as wide as the
  // largest marker level 1 may miss (the strip overlap), each plus two frames of motion. Larger
  // markers coming in are found by the next full scan.
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
  return tasks;
}

// A marker found in the previous frame, read where it is predicted: its id must read there in the
// marker's own orientation (the test every candidate of a search passes). For kSubpix the corners
// are refined here; for kEdge, Detect refines them from the prediction.
bool ReadAtPrediction(const cv::Mat& grey, const TrackedMarker& m, const DetectorConfig& config,
                      const cv::aruco::Dictionary& dictionary, const cv::aruco::DetectorParameters& p, Found& out) {
  const std::array<cv::Point2f, 4> predicted = Predict(m);
  // Inside the frame by cv::aruco's border and room for the refinement.
  const float margin = static_cast<float>(config.min_distance_to_border) + 2.0f;
  for (const auto& c : predicted) {
    if (!(c.x >= margin && c.y >= margin && c.x <= grey.cols - 1 - margin && c.y <= grey.rows - 1 - margin)) return false;
  }
  int id = -1, rotation = 0;
  if (!Identify(grey, predicted, dictionary, p, id, rotation) || id != m.id || rotation != 0) return false;
  out.id = id;
  out.corners = predicted;
  out.fit = m.fit;
  if (config.corner_refinement == CornerRefinement::kSubpix) {
    RefineMarkerCorners(grey, out.corners, dictionary.markerSize + 2 * p.markerBorderBits, p.cornerRefinementWinSize,
                        p.cornerRefinementMaxIterations, p.cornerRefinementMinAccuracy);
  }
  return true;
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

// Whether a marker found in the previous frame, predicted well inside this one, is missing: it may
// have jumped (a jolt, a cut, another camera) beyond its region, and the frame is searched whole.
// It then coasts (its region is searched for kCoastFrames frames), so one loss costs one full
// search. Measured on the drive-by: 15 full searches in its 100 frames, against 13 for the budget
// alone (one in full_search_interval), and 13 when only half the markers lost would trigger one.
bool Lost(const std::vector<TrackedMarker>& previous, const std::vector<Found>& found, const cv::Size& size) {
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
  return lost > 0;
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

  const bool tracking = state && config.tracking;
  if (!tracking) {
    pyramid.Build(grey, config.threads);
    return FullSearch(pyramid, config, *dictionary, parameters, r);
  }

  // Copy the state out: detection runs without the lock, so one Detector serves several threads
  // (their frames then interleave, which the checks below turn into full searches).
  std::vector<TrackedMarker> previous;
  cv::Mat previous_thumb;
  bool continuing = false;
  int since_full = 0;
  {
    std::lock_guard<std::mutex> lock(state->mutex);
    // Nothing tracked, nothing to gain: a frame after one without markers is searched whole, so a
    // stream without markers costs what single frames cost and a marker that appears is found at once.
    continuing = state->size == grey.size() && state->frames > 0 &&
                 std::any_of(state->markers.begin(), state->markers.end(),
                             [](const TrackedMarker& m) { return m.missed == 0; });
    previous = state->markers;
    previous_thumb = state->thumbnail;
    since_full = state->since_full;
  }
  // The thumbnail is made first only where it decides between tracking and a full search. A frame
  // searched whole anyway makes it after the pyramid, which has just read the whole frame into the
  // cache: its reads, every fourth row's, were the frame's first, each row's cache lines a miss (perf:
  // 1.6 % of Detect on 640x480 with 20 markers). The same markers; time (the libraries alternated 8
  // times, median ms a frame) 640x480 with 20 markers 1.392 -> 1.347, 1080p with one 1.684 -> 1.652,
  // the 640x480 photos 2.080 -> 2.043.
  cv::Mat thumb;
  if (continuing) {
    thumb = Thumbnail(grey);
    continuing = previous_thumb.size() == thumb.size() &&
                 cv::norm(thumb, previous_thumb, cv::NORM_L1) / thumb.total() < kSceneChange;
  }

  std::vector<Found> found, read;
  bool full = !continuing;
  if (continuing) {
    // Markers read where they are predicted need no search; the others' regions are searched.
    std::vector<TrackedMarker> searched;
    for (const auto& m : previous) {
      Found f;
      if (m.missed == 0 && m.anchored && ReadAtPrediction(grey, m, config, *dictionary, parameters, f)) {
        read.push_back(f);
      } else {
        searched.push_back(m);
      }
    }
    r.read_at_prediction = static_cast<int>(read.size());
    // The full scan's budget: one frame in full_search_interval.
    full = since_full + 1 >= config.full_search_interval;
    if (!full) {
      const std::vector<SearchTask> tasks = TrackedTasks(config, grey.size(), previous, searched);
      if (!tasks.empty()) {
        if (grey.cols % 2 == 0 && grey.rows % 2 == 0) {
          std::vector<cv::Rect> level1;
          for (const auto& t : tasks) {
            if (t.level == 1) level1.push_back(t.roi);
          }
          pyramid.BuildLevel1Regions(grey, level1, config.threads);
        } else {
          pyramid.Build(grey, config.threads);
        }
        found = Search(pyramid, tasks, false, config, *dictionary, parameters, r, read);
      }
      found.insert(found.end(), read.begin(), read.end());
      full = Lost(previous, found, grey.size());
    }
  }
  if (full) {
    pyramid.Build(grey, config.threads);
    if (thumb.empty()) thumb = Thumbnail(grey);
    found = FullSearch(pyramid, config, *dictionary, parameters, r, read);
    found.insert(found.end(), read.begin(), read.end());
  }

  {
    std::lock_guard<std::mutex> lock(state->mutex);
    state->markers = Track(found, previous);
    state->size = grey.size();
    state->thumbnail = thumb;
    state->frames += 1;
    state->since_full = full ? 0 : since_full + 1;
    (full ? state->full_searches : state->tracked_frames) += 1;
    state->read_at_prediction += static_cast<std::uint64_t>(r.read_at_prediction);
    state->searched_pixels += static_cast<std::uint64_t>(r.searched_pixels);
  }
  return found;
}

void UpdateTracked(TrackingState* state, const std::vector<ArucoTag>& tags, const std::vector<char>& anchored,
                   const std::vector<FitMemory>& fits) {
  if (!state) return;
  std::lock_guard<std::mutex> lock(state->mutex);
  for (auto& m : state->markers) {
    if (m.missed != 0) continue;
    const cv::Point2f c = Centre(m.corners);
    const float reach = 0.5f * MeanSide(m.corners) + 2.0f;
    for (size_t i = 0; i < tags.size(); ++i) {
      if (tags[i].id != m.id || cv::norm(Centre(tags[i].corners) - c) > reach) continue;
      // The velocity was measured from the unrefined corners: move it with them.
      m.velocity += Centre(tags[i].corners) - c;
      m.corners = tags[i].corners;
      m.anchored = anchored[i] != 0;
      m.fit = fits[i];
      break;
    }
  }
}

}  // namespace arucotag::internal

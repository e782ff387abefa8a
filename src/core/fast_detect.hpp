// The fast path behind Detect (internal to arucotag_core): a multi-scale candidate search whose
// candidates are decoded and refined at full resolution exactly as cv::aruco does it, plus the
// frame-to-frame tracking that restricts where the next frame is searched.
#pragma once

#include <array>
#include <cstdint>
#include <mutex>
#include <vector>

#include <opencv2/aruco.hpp>
#include <opencv2/core.hpp>

#include <arucotag/aruco_tag.hpp>
#include <arucotag/detector.hpp>

#include "decode_small.hpp"

namespace arucotag::internal {

/// What a marker's pattern fit leaves for the fit of the same marker in the next frame.
struct FitMemory {
  float blur = -1.0f;  ///< the fitted blur variance (px^2); < 0: no fit
  std::array<cv::Point2f, 4> offset{};  ///< the fitted corners minus the edge fit's, per corner
};

/// A marker found in a frame, before the id lists are applied.
struct Found {
  int id = -1;
  std::array<cv::Point2f, 4> corners{};
  FitMemory fit;  ///< read where tracking predicted it: its pattern fit of last frame (blur < 0: none)
  bool edges_fitted = false;  ///< corners already refined by RefineCornersOnEdges (from a settled fit)
  FittedPattern checked;      ///< the pattern fit that checked a small marker's reading (blur < 0: none)
};

/// What one frame leaves for the next.
struct TrackedMarker {
  int id = -1;
  std::array<cv::Point2f, 4> corners{};
  cv::Point2f velocity{0.0f, 0.0f};  ///< px/frame of the centre
  int missed = 0;  ///< frames since it was last found (its region is searched a while longer)
  /// Its refinement converged last frame: next frame it is read where it is predicted, without a
  /// search (its region is searched when it is not).
  bool anchored = false;
  FitMemory fit;  ///< its pattern fit (blur < 0 without one)
};

struct TrackingState {
  std::mutex mutex;  ///< guards everything below; held only to copy in and out, never while detecting
  cv::Size size;
  std::vector<TrackedMarker> markers;
  cv::Mat thumbnail;       ///< tiny copy of the last frame, to notice an unrelated image
  int since_full = 0;      ///< frames since the last full search
  std::uint64_t frames = 0;
  // Counters for tests and the benchmark.
  std::uint64_t full_searches = 0, tracked_frames = 0;
  std::uint64_t read_at_prediction = 0;  ///< markers found where predicted, without a search
  std::uint64_t searched_pixels = 0;     ///< pixels thresholded and traced (FrameReport's), all frames
};

/// Statistics of one call, for tests and the benchmark.
struct FrameReport {
  bool full_search = false;  ///< the whole frame was searched at every scale
  int candidates = 0;        ///< quads decoded
  int searched_pixels = 0;   ///< pixels thresholded and traced (at their pyramid level's resolution)
  int read_at_prediction = 0;  ///< tracked markers found where predicted, without a search
};

/// Whether the fast path serves this configuration: black markers with the edge-fit (kEdge) or
/// sub-pixel (kSubpix) refinement. Other refinements and inverted markers go through
/// cv::aruco::detectMarkers unchanged.
bool FastPathSupports(const DetectorConfig& config);

/// Runs the fast path on an 8-bit grey frame. Returns each marker's id and corners in cv::aruco
/// order: refined for kSubpix; for kEdge the corners cv::aruco would hand to refinement (Detect
/// applies the edge fit). With `state` non-null and config.tracking on, uses and updates the
/// markers tracked from the previous frame; `report` is optional.
std::vector<Found> FastDetect(const cv::Mat& grey, const DetectorConfig& config,
                              const cv::Ptr<cv::aruco::Dictionary>& dictionary,
                              const cv::aruco::DetectorParameters& parameters, TrackingState* state,
                              FrameReport* report = nullptr);

/// After Detect's refinement: this frame's tracked markers take their refined corners (the next
/// frame's prediction starts from them) and their pattern fit (`fits[i]` of tags[i], blur < 0
/// without one) and, with `anchored[i]` false (its refinement could not confirm it), are searched
/// for next frame rather than read where predicted. Tags are matched to markers by id and position.
/// No-op with `state` null.
void UpdateTracked(TrackingState* state, const std::vector<ArucoTag>& tags, const std::vector<char>& anchored,
                   const std::vector<FitMemory>& fits);

}  // namespace arucotag::internal

// The core's loops over independent items (internal to arucotag_core), on at most
// DetectorConfig::threads threads.
#pragma once

#include <algorithm>

#include <opencv2/core/utility.hpp>

namespace arucotag::internal {

/// The most threads a Detect call with this DetectorConfig::threads runs on: the setting, or OpenCV's
/// thread count for 0.
inline int ThreadBudget(int threads) { return threads > 0 ? threads : std::max(1, cv::getNumThreads()); }

/// body(range) for the items of `range`, on at most `threads` threads (0: as many as OpenCV uses,
/// split as cv::parallel_for_ splits it, or into `stripes` when that is given). One thread runs
/// the whole range here, without OpenCV's pool; more cut it into at most that many stripes, which
/// OpenCV's pool runs one per thread. Each item is written by the body alone, so the result is
/// the same whatever the split.
template <class Body>
void ParallelFor(const cv::Range& range, int threads, const Body& body, double stripes = -1.0) {
  if (range.empty()) return;
  if (threads == 1) {
    body(range);
    return;
  }
  if (threads > 1) stripes = stripes > 0.0 ? std::min(stripes, static_cast<double>(threads)) : threads;
  cv::parallel_for_(range, body, stripes);
}

}  // namespace arucotag::internal

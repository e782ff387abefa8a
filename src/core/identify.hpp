// Identification of the fast path's candidates (internal to arucotag_core). See identify.cpp.
#pragma once

#include <vector>

#include <opencv2/aruco.hpp>

#include <arucotag/detector.hpp>

#include "candidates.hpp"
#include "fast_detect.hpp"

namespace arucotag::internal {

/// Decodes `quads` on the full-resolution frame, keeps one marker of each that several quads found,
/// and gives each its starting or refined corners as the configured refinement wants them.
std::vector<Found> Decode(const Pyramid& pyramid, const std::vector<Quad>& quads, const DetectorConfig& config,
                          const cv::aruco::Dictionary& dictionary, const cv::aruco::DetectorParameters& p);

}  // namespace arucotag::internal

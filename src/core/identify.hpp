// Identification of the fast path's candidates (internal to arucotag_core). See identify.cpp.
#pragma once

#include <array>
#include <vector>

#include <opencv2/aruco.hpp>

#include <arucotag/detector.hpp>

#include "candidates.hpp"
#include "fast_detect.hpp"

namespace arucotag::internal {

/// Reads the black marker whose corners are `corners` (full-resolution frame) as cv::aruco reads a
/// candidate: true with its id and the rotation that puts the corners in the marker's order.
bool Identify(const cv::Mat& grey, const std::array<cv::Point2f, 4>& corners, const cv::aruco::Dictionary& dictionary,
              const cv::aruco::DetectorParameters& p, int& id, int& rotation);

/// Decodes `quads` on the full-resolution frame, keeps one marker of each that several quads found,
/// and gives each its starting or refined corners as the configured refinement wants them.
std::vector<Found> Decode(const Pyramid& pyramid, const std::vector<Quad>& quads, const DetectorConfig& config,
                          const cv::aruco::Dictionary& dictionary, const cv::aruco::DetectorParameters& p);

}  // namespace arucotag::internal

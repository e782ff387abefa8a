// Identification of the fast path's candidates (internal to arucotag_core). See identify.cpp.
#pragma once

#include <array>
#include <vector>

#include <opencv2/aruco.hpp>

#include <arucotag/detector.hpp>

#include "candidates.hpp"
#include "fast_detect.hpp"

namespace arucotag::internal {

/// Bound on the side (px) of a candidate unwarped for decoding, perspective_remove_pixel_per_cell
/// times the marker's cells: twice what dynamic_reconfigure allows with a 7x7 dictionary and one
/// border bit (9 cells of 20 px). Every candidate of a frame is unwarped: at 1440 px (8 times) a
/// frame of a few hundred candidates took 35-60 ms in the release build, 4-6 s under the fuzzer's
/// sanitizers (fuzz_config). Detector refuses configurations past it.
inline constexpr int kMaxUnwarpedSide = 360;

/// The source pixels of one row of a candidate's canonical image: offsets[x], x < size, is the
/// offset (row * step + column) in a cols x rows frame of pixel (x0 + dx x, y0 + dy x) / (w0 + dw x),
/// rounded as warpPerspective's INTER_NEAREST rounds it, or -1 outside the frame. `offsets` holds
/// size rounded up to a multiple of four.
void CanonicalRowSources(double x0, double y0, double w0, double dx, double dy, double dw, int size, int cols,
                         int rows, int step, int* offsets);

/// Reads the black marker whose corners are `corners` (full-resolution frame) as cv::aruco reads a
/// candidate: true with its id and the rotation that puts the corners in the marker's order.
bool Identify(const cv::Mat& grey, const std::array<cv::Point2f, 4>& corners, const cv::aruco::Dictionary& dictionary,
              const cv::aruco::DetectorParameters& p, int& id, int& rotation);

/// Decodes `quads` on the full-resolution frame, keeps one marker of each that several quads found,
/// and gives each its starting or refined corners as the configured refinement wants them.
std::vector<Found> Decode(const Pyramid& pyramid, const std::vector<Quad>& quads, const DetectorConfig& config,
                          const cv::aruco::Dictionary& dictionary, const cv::aruco::DetectorParameters& p);

}  // namespace arucotag::internal

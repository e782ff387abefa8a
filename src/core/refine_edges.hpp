// Internals of the edge fit (refine_edges.cpp) that the fast path uses.
#pragma once

#include <array>

#include <opencv2/core.hpp>

namespace arucotag::internal {

/// How far (px) one more pass may move a corner of a fit the fast path keeps without cv::aruco's
/// corners (RefineCornersOnEdgesSettled).
inline constexpr double kEdgeFitSettledPx = 0.05;

/// One pass of RefineCornersOnEdges (which makes two or three): for a tracked marker whose pattern fit
/// starts from it plus the offset its fit added last frame, which carries the edge fit's bias along.
int RefineCornersOnEdgesOnce(const cv::Mat& grey, std::array<cv::Point2f, 4>& corners, int cells);

/// RefineCornersOnEdges, true when it measured all four corners in its last pass and that pass, or
/// else one more, moved none of them by over `settled` px: the fit has reached its fixed point, which
/// does not depend on where it started. `corners` are RefineCornersOnEdges's whatever it returns,
/// except that its passes end early once a pass on all profiles has settled.
/// With `keep_check_pass`, a fit that has not settled keeps that one more pass (made from its passes'
/// corners whatever they measured) and is true when that pass measured all four corners.
bool RefineCornersOnEdgesSettled(const cv::Mat& grey, std::array<cv::Point2f, 4>& corners, int cells,
                                 double settled, bool keep_check_pass = false);

}  // namespace arucotag::internal

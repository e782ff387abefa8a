// Corner refinement of the fast path (internal to arucotag_core). See refine_corner.cpp.
#pragma once

#include <array>

#include <opencv2/core.hpp>

namespace arucotag::internal {

/// cv::cornerSubPix (zero zone off) for one point: `half` is the half window, px.
cv::Point2f RefineCorner(const cv::Mat& grey, cv::Point2f start, int half, int max_iterations, double epsilon);

/// Half window (px) for RefineCorner at a marker's outer corner: `configured`, but at most
/// kCornerWindowCells of a cell (`side` the marker's mean side, px; `cells` its cells a side, borders
/// included) and at least 1. A wider window takes in the edges of the cells inside the border, and the
/// corner slides towards them: cv::aruco's 5 px window left corner errors of 2-2.6 px (p95) on markers
/// of 15-30 px, worse than no refinement.
int MarkerCornerHalfWindow(float side, int cells, int configured);

/// RefineCorner on a marker's four corners with MarkerCornerHalfWindow.
void RefineMarkerCorners(const cv::Mat& grey, std::array<cv::Point2f, 4>& corners, int cells, int configured_half,
                         int max_iterations, double epsilon);

}  // namespace arucotag::internal

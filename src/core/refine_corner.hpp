// Corner refinement of the fast path (internal to arucotag_core). See refine_corner.cpp.
#pragma once

#include <array>

#include <opencv2/core.hpp>

namespace arucotag::internal {

/// cv::cornerSubPix (zero zone off) for one point: `half` is the half window, px. A corner that ends
/// further than `reach` px (the half window when 0) from `start` in x or y keeps `start`.
cv::Point2f RefineCorner(const cv::Mat& grey, cv::Point2f start, int half, int max_iterations, double epsilon,
                         float reach = 0.0f);

/// Half window (px) for RefineCorner at a marker's outer corner: `configured`, but at most
/// kCornerWindowCells of a cell (`side` the marker's mean side, px; `cells` its cells a side, borders
/// included), and at least kMinCornerHalfWindow (2 px) unless `configured` is smaller. A wider
/// window takes in the edges of the cells inside the border, and the
/// corner slides towards them: cv::aruco's 5 px window left corner errors of 2-2.6 px (p95) on markers
/// of 15-30 px, worse than no refinement.
int MarkerCornerHalfWindow(float side, int cells, int configured);

/// RefineCorner on a marker's four corners with MarkerCornerHalfWindow, each reaching at most the
/// cell-fitted half window (without the 2 px floor) from its start.
void RefineMarkerCorners(const cv::Mat& grey, std::array<cv::Point2f, 4>& corners, int cells, int configured_half,
                         int max_iterations, double epsilon);

}  // namespace arucotag::internal

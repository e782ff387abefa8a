// Corner refinement of the fast path (internal to arucotag_core). See refine_corner.cpp.
#pragma once

#include <opencv2/core.hpp>

namespace arucotag::internal {

/// cv::cornerSubPix (zero zone off) for one point: `half` is the half window, px.
cv::Point2f RefineCorner(const cv::Mat& grey, cv::Point2f start, int half, int max_iterations, double epsilon);

}  // namespace arucotag::internal

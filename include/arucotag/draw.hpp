#pragma once

#include <vector>

#include <opencv2/core.hpp>

#include <arucotag/aruco_tag.hpp>

namespace arucotag {

/// Draws each tag onto `image` in place: its outline, a filled square on corner 0 (top-left in the
/// marker's frame, so the marker's rotation is visible), its id and, when the tag has a pose, its
/// distance in metres. Works on 8-bit 1- or 3-channel images (grey images get grey drawings).
/// Throws arucotag::Error on an empty image or any other channel count or depth.
void DrawDetections(cv::Mat& image, const std::vector<ArucoTag>& tags);

}  // namespace arucotag

#pragma once

#include <array>

#include <opencv2/core.hpp>

namespace arucotag {

/// Moves each corner of a marker to the intersection of its two border edges, each a line fitted to
/// sub-pixel edge points found where the grey profile across the edge crosses halfway between its
/// dark and light sides. cv::cornerSubPix pulls convex corners 0.1-0.2 px inwards (measured on
/// exactly rendered squares); this has no such bias, which matters for PnP range on small markers.
/// Lines are fitted only over the part of each edge nearest the corner, so mild lens distortion
/// (curved edges) costs little. `grey` is the 8-bit image the corners were found in; corners are in
/// cv::aruco order. A corner whose edges cannot be measured (low contrast, image border, edges too
/// short) keeps its input position. `cells` is the marker's width in cells including its black
/// border (marker bits + 2), which bounds how far across an edge it is safe to look. Returns how many
/// corners were moved in the last pass.
int RefineCornersOnEdges(const cv::Mat& grey, std::array<cv::Point2f, 4>& corners, int cells);

}  // namespace arucotag

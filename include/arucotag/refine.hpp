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

/// Moves the four corners so that the marker's known pattern, projected through the homography they
/// define, explains the grey values of every pixel of the marker and of half a cell of its quiet
/// zone: each pixel is modelled as brightness (with a linear gradient) plus contrast times the exact
/// fraction of its area covered by black cells, blurred by a Gaussian whose width is fitted too
/// (damped Gauss-Newton, Huber weights). It uses every cell boundary, not only the outer border, so
/// it is what makes the pose of small (15-56 px) markers right. `black` is the marker's cells
/// including its border, CV_8UC1, square, non-zero = black (see MarkerCells); corners are in cv::aruco
/// order and should be within about a pixel already (RefineCornersOnEdges). Markers over about 95 px
/// are fitted on an even lattice of about 6000 of their pixels, which bounds the cost (0.02 px instead
/// of 0.01). Returns false and leaves
/// the corners as they were when the fit cannot be trusted or is not meant for the marker: over 256 px
/// a side, mostly outside the image, no contrast, a fit that moves a corner more than 2 px, or one that leaves over 5 % of the pixels off
/// by more than a quarter of the black-white contrast (occlusion, a wrong pattern, ink that bleeds).
bool RefineCornersOnPattern(const cv::Mat& grey, const cv::Mat& black, std::array<cv::Point2f, 4>& corners);

}  // namespace arucotag

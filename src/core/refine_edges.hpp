// Internals of the edge fit (refine_edges.cpp) that the fast path uses.
#pragma once

#include <array>

#include <opencv2/core.hpp>

namespace arucotag::internal {

/// How far (px) one more pass may move a corner of a fit the fast path keeps without cv::aruco's
/// corners (RefineCornersOnEdgesSettled). The passes contract: after a full pass that moved a corner
/// by up to this, the next moves it by a few thousandths (640x480/50: 0.040 px, then 0.006 px at the
/// median), so the fit is that close to its fixed point. At 0.05 px a third of the small markers paid
/// for a second full pass (or a check pass) to show it. At 0.1 px (stop 62), over bench_dump's corpus:
/// the same ids and pattern-fit choices; 381 of 2508 markers' corners moved, by 0.002 px at the median
/// (at most 0.067 px, one photo marker). The probe's corner errors on the bench renders: medians within
/// 0.0004 px (640x480/50 0.0261 -> 0.0265), p95s within 0.0012 px. Callgrind of Detect on 640x480/50
/// 108.85 -> 103.18 M, /20 73.69 -> 71.28 M.
inline constexpr double kEdgeFitSettledPx = 0.1;

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

/// How blurred a marker's edges are: the variance (px^2) of the grey-level ramp across them, the
/// median over profiles across the middle half of each edge (reaching kBlurProfileReach px either
/// side, less than the black border: a marker of 32 px has 3.6 px of it with the 9 cells of a 7x7
/// dictionary, where DetectorConfig::pattern_fit_sharp_max_side's floor lies). It counts the pixel's own
/// width and the bilinear reading's, so a sharp edge reads about 0.3-0.5 px^2: renders with a 0.5 px
/// Gaussian 0.39-0.50, the sample recording's jpeg frames with motion blur 0.67-1.24, the distant
/// set's 0.8 px blur 0.82-0.84. Negative when fewer than four profiles had any contrast.
inline constexpr double kBlurProfileReach = 2.5;
double EdgeBlurVariance(const cv::Mat& grey, const std::array<cv::Point2f, 4>& corners);

}  // namespace arucotag::internal

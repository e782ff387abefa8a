// Internals of the whole-pattern corner fit (refine_pattern.cpp) that the tests check.
#pragma once

#include <array>
#include <cstddef>
#include <vector>

#include <opencv2/core.hpp>

namespace arucotag::internal {

/// How many pixels RefineCornersOnPattern would fit for a marker of `cells` cells (border included)
/// at `corners` in `grey`: every pixel of the marker and its quiet-zone strip, every other one for
/// cells of 4 px or more, and at most about 6000 for markers over about 95 px (a sparser lattice).
size_t PatternFitSampleCount(const cv::Mat& grey, int cells, const std::array<cv::Point2f, 4>& corners);

/// The area of each pixel of a `size` image (pixel (x, y) is [x - 0.5, x + 0.5] x [y - 0.5, y + 0.5])
/// that the simple polygon covers, CV_64F: the pattern fit's coverage (its edges walked through the
/// pixels they cross, the signed area of each piece accumulated along its row), for any polygon.
cv::Mat PolygonCoverage(const std::vector<cv::Point2d>& polygon, const cv::Size& size);

/// How many times the fit has evaluated its cost (and normal equations) on this thread so far: what
/// fits cost, counted rather than timed.
size_t PatternFitEvaluations();

/// How many blur variances the fits' starts have tried on this thread so far (each a blur of the
/// coverage and a brightness-and-contrast fit): one for a fit given its start variance, three or four
/// for one that scans kStartBlurVariances.
size_t PatternFitBlurStarts();

/// RefineCornersOnPattern with the fit's blur: `blur_variance` (px^2) in, the variance to start from
/// (a tracked marker's fit of the last frame; < 0: the usual start, which tries four), out, the
/// fitted one when it returns true. A Gauss-Newton step that moves no corner by `last_step` px or
/// more is taken without evaluating the cost where it lands, and ends the fit: kColdLastStep from
/// the edge fit's corners, kCarriedLastStep from a start already at about the fit's accuracy (a
/// tracked marker's edge fit moved by last frame's fit offset). Measured on the drive-by in video mode
/// (439 carried fits): at 0.1 px 190 of them needed a second evaluation, and raising the bound to
/// 0.15 px cut the median frame's instructions by 10 % for a corner error p95 of 0.0599 px against
/// 0.0588 (median 0.02156 against 0.02153); 0.2 px gave 0.0621, 0.3 px 0.0662. Cold fits ended at
/// 0.02 px until stop 30. At 0.05 px the default detector's time on the real 640x480 photos, 640x480
/// with 20 markers, 720p with 5 and tag36h11 fell by 2-12 % (bench_detect), with corner error medians
/// at most 0.0012 px higher on the renders and p95 the same or lower; bench_pose's flips
/// unchanged at 1-10 m on two seeds, 2 more of 260 fused ones at 10-15 m on one (where flips are
/// `ambiguity`'s to report). 0.1 px saved 8-12 % but flipped one more pose at 6-10 m.
inline constexpr double kColdLastStep = 0.05;
inline constexpr double kCarriedLastStep = 0.15;
bool RefineCornersOnPatternFrom(const cv::Mat& grey, const cv::Mat& black, std::array<cv::Point2f, 4>& corners,
                                float& blur_variance, double last_step);

}  // namespace arucotag::internal

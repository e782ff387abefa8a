// Second-chance decoder for tiny marker candidates (internal to arucotag_core). cv::aruco decodes a
// candidate by warping it to 4 px per cell and voting over each cell's inner pixels with nearest-
// neighbour sampling: on a marker 12-30 px wide, and on one tilted so far that its cells are barely
// a pixel in one direction, a one-pixel error of the contour's corners or the blur of a 1.25 px cell
// flips bits, and the candidate is rejected. This decoder estimates each cell's grey level from all
// the pixels it touches instead.
#pragma once

#include <array>
#include <vector>

#include <opencv2/aruco.hpp>
#include <opencv2/core.hpp>

#include "geometry.hpp"

namespace arucotag::internal {

/// Candidates with a mean side (px) below this get the second chance. Above it cv::aruco's own
/// decoding has 5 px per cell or more and a rejection is a real one.
constexpr float kSmallCandidateMaxSide = 30.0f;

/// At most this many of a frame's rejected candidates get the second chance (DecodeRejected, and
/// the fast path's Decode), the biggest first: each costs 0.05-0.2 ms, and a noisy or textured frame
/// gives hundreds. The test frames (real photos, rendered scenes) give at most 46.
constexpr size_t kMaxSmallCandidates = 96;

/// Whether a candidate quad with this mean side (px) gets the second chance: under
/// kSmallCandidateMaxSide, and at least one pixel per cell of a marker with `cells` cells a side
/// (its bits and borders): below that no cell can be read (an 80x80 frame of equalized noise gave 75
/// such quads of 1-3 px, of 77 candidates).
inline bool SmallCandidateSide(float side, int cells) { return side >= cells && side < kSmallCandidateMaxSide; }

/// Sub-pixel samples per pixel and axis when the small-marker decoder measures how much of each
/// pixel each cell covers.
constexpr int kCoverageSamples = 4;

/// The cells of a pixel's kCoverageSamples^2 samples, row by row, into `cells`: cy * n + cx, or n * n
/// outside the n x n square. The pixel's corners, in cell coordinates, are p00, p00 + dx, p00 + dy and
/// p00 + dx + dy + dxy; sample (i, j) is row + step * fx, with fx = (i + 0.5) / kCoverageSamples,
/// row = p00 + dy * fy, step = dx + dxy * fy and fy likewise. Computed four samples at a time in the
/// double arithmetic of that formula, one rounding per product and sum, so each lands in the cell
/// the scalar formula (with floor) gives.
void CoverageSampleCells(const cv::Point2d& p00, const cv::Point2d& dx, const cv::Point2d& dy, const cv::Point2d& dxy,
                         int n, int* cells);

/// The cells of a pixel's samples as CoverageSampleCells places them, and how many samples fall in
/// each: `cells` ascending (n * n, outside the square, last) and `counts` alongside; returns how many
/// cells. Only for a pixel whose corners lie within three columns and three rows of cells, clear of
/// their lines by 1e-9 cells (nearly every pixel of a marker over a pixel per cell): -1 otherwise,
/// with nothing counted. n > 2.
int CoverageCounts(const cv::Point2d& p00, const cv::Point2d& dx, const cv::Point2d& dy, const cv::Point2d& dxy, int n,
                   int* cells, int* counts);

/// Solves normal * x = rhs (CV_64F, normal symmetric positive definite, rhs one column) as
/// cv::solve(DECOMP_CHOLESKY) does, visiting only each row's envelope (from its first non-zero on):
/// the cell estimate's normal matrix couples each cell with its neighbours alone, so this costs a
/// tenth of the dense factorisation. `normal` is overwritten, `rhs` becomes x; false when the
/// matrix is not positive definite.
bool SolveEnvelope(cv::Mat& normal, cv::Mat& rhs);
/// The same on a row-major m x m `normal` whose row i is read from first[i] (<= i) to the diagonal
/// only (the rest of the lower triangle zero, the upper never read); `b` becomes x.
bool SolveEnvelope(double* normal, int m, const int* first, double* b);

/// The pattern fit (RefineCornersOnPattern) that checked a decoded marker: where it put the corners
/// (cv::aruco order) and the blur variance it found. Detect takes it as the marker's refinement
/// instead of fitting the same pattern again.
struct FittedPattern {
  float blur = -1.0f;  ///< px^2; < 0: no fit
  std::array<cv::Point2f, 4> corners{};
};

/// A marker the small decoder identified.
struct SmallMarker {
  int id = -1;
  std::array<cv::Point2f, 4> corners{};  ///< cv::aruco order: corner 0 is the marker's top-left
  FittedPattern fit;                     ///< PatternExplainsPixels' fit from `corners`
};

/// Decodes a small candidate quad (any corner order) of an 8-bit grey frame. Tries the quad as the
/// marker's black square, then as the outline of its quiet zone (the white margin, which is the only
/// contour cv::aruco finds around a steeply tilted marker) with the black square located inside it
/// from the grey levels. Cell grey levels are a least-squares fit of the pixels around the marker,
/// each pixel the area-weighted mean of the cells it covers through the quad's homography; they are
/// split into black and white by Otsu's threshold over the cells; a marker
/// needs a clear gap between the two, a whole black border (white with `detect_inverted`, bits then
/// inverted), a quiet zone around it, one dictionary code and rotation that the known cells match but
/// at most a few (2 of tag36h11's 36 cells, none of DICT_4X4_50's; see kMaxChanceCorrected) and no
/// other as close, and a pattern that explains the pixels (PatternExplainsPixels).
/// Samples outside the frame are skipped (Detect's candidates keep min_distance_to_border from it).
/// Returns false for quads whose side SmallCandidateSide refuses, or not a marker.
bool DecodeSmall(const cv::Mat& grey, const std::array<cv::Point2f, 4>& candidate,
                 const cv::aruco::Dictionary& dictionary, int border_bits, bool detect_inverted, SmallMarker& marker);

/// How many times the small decoder has estimated a candidate's cells (its costly step) on this
/// thread so far: what DecodeSmall costs, counted rather than timed.
size_t SmallCellEstimates();

/// Whether marker `id`'s printed pattern, fitted to the frame from `corners` (cv::aruco order) by
/// RefineCornersOnPattern, explains the pixels there. A reading that merely happens to match a code
/// (a bigger marker's inner cells read on a coarser grid, texture) leaves many pixels unexplained
/// and is refused: the second chance's check against false positives. `fit`, when given, receives
/// the fit of a pattern that does.
bool PatternExplainsPixels(const cv::Mat& grey, const cv::aruco::Dictionary& dictionary, int id, int border_bits,
                           const std::array<cv::Point2f, 4>& corners, FittedPattern* fit = nullptr);

/// The candidates of `rejected` DecodeRejected tries, as indices in their order: the quads whose mean
/// side SmallCandidateSide accepts, at most kMaxSmallCandidates of them, the biggest.
std::vector<size_t> SmallCandidates(const std::vector<std::vector<cv::Point2f>>& rejected, int cells);

/// The second chance of cv::aruco::detectMarkers' rejected candidates: every SmallCandidates one DecodeSmall
/// identifies, except where a marker of the same id was already found (`found`, or an earlier
/// rejected candidate) within cv::aruco's min_marker_distance_rate. Corners are refined with
/// cv::cornerSubPix when the parameters ask for CORNER_REFINE_SUBPIX, as cv::aruco refines its own.
std::vector<SmallMarker> DecodeRejected(const cv::Mat& grey, const std::vector<std::vector<cv::Point2f>>& rejected,
                                        const std::vector<std::vector<cv::Point2f>>& found_corners,
                                        const std::vector<int>& found_ids, const cv::aruco::Dictionary& dictionary,
                                        const cv::aruco::DetectorParameters& parameters);

}  // namespace arucotag::internal

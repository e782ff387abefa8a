// Candidate search of the fast path (internal to arucotag_core): the frame pyramid, the search
// tasks that say which region of which level is thresholded with which window, and the quads they
// find, filtered and merged as cv::aruco does it. See candidates.cpp.
#pragma once

#include <array>
#include <vector>

#include <opencv2/core.hpp>
#include <opencv2/imgproc.hpp>

#include <arucotag/detector.hpp>

#include "geometry.hpp"

namespace arucotag::internal {

/// Pyramid levels: full, half and quarter resolution.
constexpr int kLevels = 3;

/// One threshold window per level, and the smallest marker side (px at that level) a reduced level
/// looks for: below it the finer level's contour is the one to trust.
struct LevelSearch {
  int window;
  int min_side;
};
constexpr LevelSearch kLevelSearch[kLevels] = {{7, 0}, {11, 6}, {5, 12}};

/// A square candidate in full-resolution pixels, corners clockwise as cv::aruco orders them.
struct Quad {
  std::array<cv::Point2f, 4> corners{};
  int level = 0;      ///< pyramid level it was found at (0 = full resolution)
  float area = 0.0f;  ///< px^2, full resolution
  int perimeter = 0;  ///< contour length at its level, px
  cv::Rect box;       ///< its contour's bounding box, level pixels
  bool hole = false;  ///< its contour is a hole's border (a light region inside a dark one)
};

/// cv::resize(src, dst, (src.cols / 2, src.rows / 2), 0, 0, INTER_AREA) of a CV_8UC1 image, the same
/// pixels: where both sides are even and the CPU has AVX2 each is (a + b + c + d + 2) >> 2 of its 2x2
/// block, as OpenCV's own even-size path computes it, 32 to a step, on at most `threads` threads (see
/// ParallelFor); otherwise cv::resize itself. `dst` keeps its buffer when it already has the size (a
/// region of a bigger image stays one).
void HalveArea(const cv::Mat& src, cv::Mat& dst, int threads = 0);

/// cv::adaptiveThreshold(src, binary, 1, ADAPTIVE_THRESH_MEAN_C, THRESH_BINARY_INV, window, constant)
/// with a 1-pixel zero frame around it (what BorderScan reads), of a CV_8UC1 image: kForeground
/// where src + floor(constant) <= round(box mean), edges replicated. Windows 5, 7 and 11 with
/// 0 <= floor(constant) (and (255 + floor(constant)) * window^2 < 2^15) take 16-bit box sums, the
/// rest cv::adaptiveThreshold itself; the same pixels either way.
void Threshold(const cv::Mat& src, int window, double constant, cv::Mat& out);

/// The frame at full, half and quarter resolution (INTER_AREA), level 0 sharing the caller's pixels;
/// built on at most `threads` threads (DetectorConfig::threads).
struct Pyramid {
  std::array<cv::Mat, kLevels> images;
  void Build(const cv::Mat& grey, int threads = 0) {
    images[0] = grey;
    for (int l = 1; l < kLevels; ++l) HalveArea(images[l - 1], images[l], threads);
  }
  /// Level 0, and level 1 only inside `regions` (level-1 pixels; elsewhere undefined): what a frame
  /// searched in a few regions needs. Only for frames of even width and height, where the 2x
  /// INTER_AREA of Build averages 2x2 blocks, so the regions get Build's pixels.
  void BuildLevel1Regions(const cv::Mat& grey, const std::vector<cv::Rect>& regions, int threads = 0) {
    CV_Assert(grey.cols % 2 == 0 && grey.rows % 2 == 0);
    images[0] = grey;
    images[1].create(grey.rows / 2, grey.cols / 2, CV_8UC1);
    for (int l = 2; l < kLevels; ++l) images[l].release();
    const cv::Rect level1(0, 0, images[1].cols, images[1].rows);
    for (const cv::Rect& region : regions) {
      const cv::Rect r = region & level1;
      if (r.empty()) continue;
      cv::Mat out = images[1](r);
      HalveArea(grey(cv::Rect(2 * r.x, 2 * r.y, 2 * r.width, 2 * r.height)), out, threads);
    }
  }
};

/// One region of one pyramid level to search, with its threshold window and contour length limits.
struct SearchTask {
  int level = 0;
  int window = 0;
  cv::Rect roi;  // level pixels
  int min_perimeter = 0, max_perimeter = 0;  // level pixels
};

/// A task at `level` over `roi` (level pixels) with cv::aruco's perimeter limits; window 0 is the level's.
SearchTask MakeTask(const DetectorConfig& config, const cv::Size& frame, int level, const cv::Rect& roi,
                    int window = 0);

/// Runs every task (in parallel) and appends the quads they find to `quads`.
void RunTasks(const Pyramid& pyramid, const std::vector<SearchTask>& tasks, const DetectorConfig& config,
              std::vector<Quad>& quads);

/// Level-0 strips of one region (tasks of the same columns, each reaching past the next one's top)
/// each keep only the quads whose corners lie clear of their own inner edges, so a quad across the
/// seam between two, too tall for the overlap, is found by neither at full resolution, where a single
/// task over the region finds it. For each coarser quad across a seam this searches its
/// neighbourhood at full resolution and appends what neither strip keeps: the quads then do not
/// depend on how many strips (threads) searched the region.
void CompleteSeams(const Pyramid& pyramid, const std::vector<SearchTask>& tasks, const DetectorConfig& config,
                   std::vector<Quad>& quads);

/// Sorts quads by their content (level, corners, then the rest), so that what is made of them does
/// not depend on the order the tasks (threads) listed them in.
void SortQuads(std::vector<Quad>& quads);

/// Whether two quads are one candidate for cv::aruco's _filterTooCloseCandidates at this `rate`.
bool TooClose(const Quad& a, const Quad& b, double rate);

/// cv::aruco's _filterTooCloseCandidates within each pyramid level: the biggest of quads too close.
std::vector<Quad> MergeQuads(std::vector<Quad> quads, double rate);

/// Appends the quads cv::aruco's own candidate search (every configured window) finds at `corners`.
void OpenCvQuadsNear(const Pyramid& pyramid, const DetectorConfig& config, const std::array<cv::Point2f, 4>& corners,
                     std::vector<Quad>& found);

/// Replaces `decoded`'s corners with those cv::aruco would start from there; false if it finds none.
bool CornersAsOpenCv(const Pyramid& pyramid, const DetectorConfig& config, Quad& decoded);

}  // namespace arucotag::internal

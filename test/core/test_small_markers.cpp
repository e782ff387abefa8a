// Recall of tiny markers (9-22 px) and the second-chance decoder's false positives: a 0.15 m
// DICT_4X4_50 marker seen by the rover camera at 7-12 m, tilted up to 60 degrees.
#include <algorithm>
#include <cmath>
#include <cstdio>
#include <limits>
#include <map>
#include <string>
#include <vector>

#include <gtest/gtest.h>
#include <opencv2/aruco.hpp>
#include <opencv2/imgproc.hpp>

#include "candidates.hpp"
#include "decode_small.hpp"
#include "identify.hpp"
#include "refine_pattern.hpp"
#include "scene.hpp"

namespace arucotag {
namespace {

constexpr int kId = 7;

// The marker at `range` m, slightly right of and above the optical axis, tilted and rolled.
sim::Marker FarMarker(double range, double tilt, double roll) {
  return sim::FacingCamera(kId, 0.15, {0.1 * range, -0.05 * range, range}, tilt, 0.3 * tilt, roll);
}

cv::Mat RenderGrey(const sim::Camera& camera, const std::vector<sim::Marker>& markers, unsigned seed = 1) {
  sim::RenderOptions options;
  options.seed = seed;
  cv::Mat grey;
  PreprocessFrame(sim::RenderScene(camera, markers, options), grey);
  return grey;
}

DetectorConfig FullSearch() {
  DetectorConfig config;
  config.fast_path = false;
  return config;
}

// Largest distance (px) of a tag's corners from the true ones, in the order reported.
double MaxCornerError(const ArucoTag& tag, const std::array<cv::Point2f, 4>& truth) {
  double error = 0.0;
  for (int k = 0; k < 4; ++k) error = std::max(error, static_cast<double>(cv::norm(tag.corners[k] - truth[k])));
  return error;
}

// The cell estimate's solver against cv::solve (DECOMP_CHOLESKY) on normal matrices shaped like the
// estimate's: n x n cells, each coupled with its 8 neighbours, plus a quiet-zone unknown coupled
// with the border cells, and a ridge on the diagonal; and on a dense one. Same solution (to
// rounding), and the same refusal of a matrix that is not positive definite.
TEST(SmallMarkers, EnvelopeSolverMatchesOpenCvCholesky) {
  cv::RNG rng(6);
  for (int trial = 0; trial < 40; ++trial) {
    const int n = 3 + trial % 6, m = n * n + 1;
    const bool dense = trial % 10 == 9;
    cv::Mat design(6 * m, m, CV_64F, cv::Scalar(0));  // rows: pixels; columns: the unknowns they see
    for (int r = 0; r < design.rows; ++r) {
      const int cy = rng.uniform(0, n), cx = rng.uniform(0, n);
      for (int dy = 0; dy <= 1; ++dy) {
        for (int dx = 0; dx <= 1; ++dx) {
          const int y = cy + dy, x = cx + dx;
          const int k = (y < n && x < n) ? y * n + x : n * n;  // past the edge: the quiet zone
          design.at<double>(r, k) += rng.uniform(0.05, 1.0);
        }
      }
      if (dense) design.at<double>(r, rng.uniform(0, m)) += 0.5;
    }
    cv::Mat normal = design.t() * design + 0.02 * cv::Mat::eye(m, m, CV_64F);
    cv::Mat rhs(m, 1, CV_64F);
    rng.fill(rhs, cv::RNG::UNIFORM, 0.0, 255.0);
    cv::Mat expected;
    ASSERT_TRUE(cv::solve(normal, rhs, expected, cv::DECOMP_CHOLESKY));
    cv::Mat a = normal.clone(), x = rhs.clone();
    ASSERT_TRUE(internal::SolveEnvelope(a, x)) << "trial " << trial;
    EXPECT_LE(cv::norm(x, expected, cv::NORM_INF), 1e-9 * cv::norm(expected, cv::NORM_INF)) << "trial " << trial;
  }
  // (4 x 4: cv::solve inverts 3 x 3 systems by formula, whatever the method.)
  cv::Mat indefinite = (cv::Mat_<double>(4, 4) << 1, 0, 0, 2, 0, 1, 0, 0, 0, 0, 1, 0, 2, 0, 0, 1);
  cv::Mat b = cv::Mat::ones(4, 1, CV_64F), unused;
  EXPECT_FALSE(cv::solve(indefinite, b, unused, cv::DECOMP_CHOLESKY));
  EXPECT_FALSE(internal::SolveEnvelope(indefinite, b));
}

// The cell estimate's coverage samples, four at a time, against the formula one sample at a time
// with floor: the same cell for every sample, including samples exactly on a cell line, an ulp
// either side of one, outside the square on each side, NaN and past int's range. A bounds test that
// truncates (x > -1 for x >= 0) puts samples just left of the square inside it and fails.
TEST(SmallMarkers, CoverageSamplesLandInTheScalarFormulasCells) {
  // Sample (i, j) of the pixel with corners p00, p00 + dx, p00 + dy, p00 + dx + dy + dxy.
  const auto sample = [](const cv::Point2d& p00, const cv::Point2d& dx, const cv::Point2d& dy,
                         const cv::Point2d& dxy, int i, int j) {
    const double fy = (j + 0.5) / internal::kCoverageSamples, fx = (i + 0.5) / internal::kCoverageSamples;
    const cv::Point2d row = p00 + dy * fy, step = dx + dxy * fy;
    return row + step * fx;
  };
  cv::RNG rng(25);
  int compared = 0, on_line = 0, outside = 0;
  for (int trial = 0; trial < 50000; ++trial) {
    const int n = 4 + trial % 11;
    const double scale = rng.uniform(0.3, 1.5);  // cells per pixel
    cv::Point2d p00(rng.uniform(-1.0, n + 0.5), rng.uniform(-1.0, n + 0.5));
    cv::Point2d dx(scale * rng.uniform(-1.0, 1.0), scale * rng.uniform(-1.0, 1.0));
    cv::Point2d dy(-dx.y + rng.uniform(-0.1, 0.1), dx.x + rng.uniform(-0.1, 0.1));
    cv::Point2d dxy(rng.uniform(-0.01, 0.01), rng.uniform(-0.01, 0.01));
    switch (trial % 6) {
      case 0:  // axis-aligned, four cells a pixel from half a cell off a line: every sample on a line
        p00 = cv::Point2d(std::floor(p00.x) - 0.5, std::floor(p00.y) - 0.5);
        dx = cv::Point2d(4.0, 0.0), dy = cv::Point2d(0.0, 4.0), dxy = cv::Point2d(0.0, 0.0);
        break;
      case 1:  // axis-aligned, the first column of samples an ulp either side of a cell line
        p00.x = std::nextafter(std::floor(p00.x) - 0.0625, trial % 12 < 6 ? -1e9 : 1e9);
        dx = cv::Point2d(0.5, 0.0), dy = cv::Point2d(0.0, 0.5), dxy = cv::Point2d(0.0, 0.0);
        break;
      case 2:  // far outside, past int's range, or not a number
        p00.x = trial % 18 == 2 ? std::numeric_limits<double>::quiet_NaN() : rng.uniform(-1.0, 1.0) * 1e12;
        break;
      case 3:  // the second sample of each row exactly on the square's left edge (x = -p + p)
        dy = cv::Point2d(0.0, dy.y), dxy = cv::Point2d(0.0, 0.0);
        p00.x = -(dx.x * 0.375);
        break;
      default:
        break;
    }
    int cells[internal::kCoverageSamples * internal::kCoverageSamples];
    internal::CoverageSampleCells(p00, dx, dy, dxy, n, cells);
    for (int j = 0; j < internal::kCoverageSamples; ++j) {
      for (int i = 0; i < internal::kCoverageSamples; ++i) {
        const cv::Point2d s = sample(p00, dx, dy, dxy, i, j);
        const double cx = std::floor(s.x), cy = std::floor(s.y);
        const int expected =
            (cx >= 0 && cy >= 0 && cx < n && cy < n) ? static_cast<int>(cy) * n + static_cast<int>(cx) : n * n;
        ASSERT_EQ(cells[j * internal::kCoverageSamples + i], expected) << "trial " << trial << " sample " << i << "," << j;
        ++compared;
        outside += expected == n * n;
        on_line += s.x == cx;
      }
    }
  }
  std::printf("%d samples, %d outside the square, %d on a cell line\n", compared, outside, on_line);
  EXPECT_GT(outside, compared / 10);
  EXPECT_GT(on_line, 10000);
}

// The counted cells of a pixel against CoverageSampleCells's sixteen, counted one by one: the same
// cells with the same counts wherever CoverageCounts takes the pixel, which it must do for nearly
// every pixel a marker over a pixel per cell gives; it leaves only pixels over more than three
// columns or rows of cells, or within 1e-9 of the lines bounding them. Corners exactly on cell lines
// (a pixel grid aligned with the cells), an ulp either side of them, across each edge of the square,
// wholly outside it and NaN.
TEST(SmallMarkers, CoverageCountsAreTheSampleCellsCounted) {
  cv::RNG rng(26);
  int counted = 0, left = 0, aligned_left = 0, outside = 0, several = 0, plain = 0, plain_left = 0;
  for (int trial = 0; trial < 60000; ++trial) {
    const int n = 3 + trial % 12;
    const double scale = rng.uniform(0.2, 1.0);  // cells per pixel: 1-5 px a cell
    const double angle = rng.uniform(0.0, 2.0 * CV_PI);
    cv::Point2d p00(rng.uniform(-1.5, n + 0.5), rng.uniform(-1.5, n + 0.5));
    cv::Point2d dx(scale * std::cos(angle), scale * std::sin(angle));
    cv::Point2d dy(-dx.y * rng.uniform(0.8, 1.2), dx.x * rng.uniform(0.8, 1.2));
    cv::Point2d dxy(rng.uniform(-0.02, 0.02) * scale, rng.uniform(-0.02, 0.02) * scale);
    bool aligned = false;
    switch (trial % 8) {
      case 0:  // the grid of a marker square to the pixels: corners on cell lines
        aligned = true;
        p00 = cv::Point2d(std::floor(p00.x) + 0.5 * (trial % 3), std::floor(p00.y));
        dx = cv::Point2d(0.5, 0.0), dy = cv::Point2d(0.0, 0.5), dxy = cv::Point2d(0.0, 0.0);
        break;
      case 1:  // a corner an ulp either side of a cell line
        p00.x = std::nextafter(std::round(p00.x), trial % 16 < 8 ? -1e9 : 1e9);
        break;
      case 2:  // far outside, or not a number
        p00.y = trial % 16 == 2 ? std::numeric_limits<double>::quiet_NaN() : n + 2.0 + rng.uniform(0.0, 1e6);
        break;
      default:
        ++plain;
        break;
    }
    int sample_cells[internal::kCoverageSamples * internal::kCoverageSamples];
    internal::CoverageSampleCells(p00, dx, dy, dxy, n, sample_cells);
    std::map<int, int> expected;
    for (const int cell : sample_cells) ++expected[cell];
    int cells[internal::kCoverageSamples * internal::kCoverageSamples];
    int counts[internal::kCoverageSamples * internal::kCoverageSamples];
    const int found = internal::CoverageCounts(p00, dx, dy, dxy, n, cells, counts);
    if (found < 0) {
      ++left;
      aligned_left += aligned;
      plain_left += trial % 8 > 2;
      continue;
    }
    ++counted;
    std::map<int, int> got;
    for (int i = 0; i < found; ++i) {
      ASSERT_GT(counts[i], 0) << "trial " << trial;
      if (i > 0) {
        ASSERT_LT(cells[i - 1], cells[i]) << "trial " << trial;  // ascending, each once
      }
      got[cells[i]] = counts[i];
    }
    ASSERT_EQ(got, expected) << "trial " << trial;
    outside += expected.count(n * n) > 0;
    several += found > 1;
  }
  std::printf("%d pixels counted (%d with the outside, %d over several cells), %d left to the samples (%d of %d "
              "placed at random)\n", counted, outside, several, left, plain_left, plain);
  // Pixels placed at random are left only where they reach over more than three columns or rows (at
  // 1-1.25 px a cell, turned and sheared).
  EXPECT_LT(plain_left, plain / 50);
  EXPECT_GT(outside, counted / 10);
  EXPECT_GT(several, counted / 2);
  EXPECT_GT(aligned_left, 0);  // corners on the lines inside the square: left, within 1e-9 of them
}

// Every marker plain cv::aruco::detectMarkers finds, the fast path finds too: at these sizes the
// fast path's own contours differ from cv::aruco's by a pixel, which used to flip its reading.
TEST(SmallMarkers, FastPathFindsEveryMarkerOpenCvFinds) {
  const auto dictionary = cv::aruco::getPredefinedDictionary(cv::aruco::DICT_4X4_50);
  int opencv_found = 0, fast_found = 0;
  for (const bool distorted : {false, true}) {
    const sim::Camera camera = test::RoverCamera(distorted);
    for (const double range : {7.0, 10.0, 12.0}) {
      for (const double tilt : {0.0, 30.0, 45.0}) {
        for (const double roll : {7.0, 97.0, 187.0, 277.0}) {
          const cv::Mat grey = RenderGrey(camera, {FarMarker(range, tilt, roll)});
          std::vector<std::vector<cv::Point2f>> corners;
          std::vector<int> ids;
          cv::aruco::detectMarkers(grey, dictionary, corners, ids, cv::aruco::DetectorParameters::create());
          const auto tags = Detect(grey, Detector());
          ASSERT_LE(tags.size(), 1u) << range << " m, tilt " << tilt << ", roll " << roll;
          for (const auto& tag : tags) EXPECT_EQ(tag.id, kId);
          if (!ids.empty()) {
            ++opencv_found;
            EXPECT_EQ(tags.size(), 1u) << "cv::aruco finds it, Detect does not: " << range << " m, tilt " << tilt
                                       << ", roll " << roll << (distorted ? ", distorted" : "");
          }
          fast_found += static_cast<int>(tags.size());
        }
      }
    }
  }
  // 72 views: cv::aruco reads 60 (most 12 m ones at 30-45 degrees not), Detect all of them.
  EXPECT_EQ(opencv_found, 60);
  EXPECT_EQ(fast_found, 72);
}

// At 10 m and 60 degrees the marker is 15 x 7.5 px, cells 1.25 px across: only its quiet zone's
// outline is a candidate, and cv::aruco cannot read it. Both paths decode it, the right way up.
TEST(SmallMarkers, SteeplyTiltedMarkerAt10mIsDecoded) {
  for (const bool distorted : {false, true}) {
    const sim::Camera camera = test::RoverCamera(distorted);
    for (const double roll : {7.0, 97.0, 187.0, 277.0}) {
      const sim::Marker marker = FarMarker(10.0, 60.0, roll);
      const cv::Mat grey = RenderGrey(camera, {marker});
      const auto truth = sim::ProjectCorners(camera, marker);
      for (const bool fast : {true, false}) {
        const auto tags = Detect(grey, fast ? Detector() : Detector(FullSearch()));
        ASSERT_EQ(tags.size(), 1u) << "roll " << roll << (fast ? " fast" : " full") << (distorted ? " distorted" : "");
        EXPECT_EQ(tags[0].id, kId);
        // Corner 0 is the marker's top-left: a wrong rotation would put corners 7-15 px away.
        EXPECT_LT(MaxCornerError(tags[0], truth), 1.5) << "roll " << roll << (fast ? " fast" : " full");
      }
    }
  }
}

// The pattern fit that checks a second-chance reading is the marker's refinement: Detect does not
// fit the same pattern again from the edge fit's corners. Counted on this thread: the fits with the
// refinement's pattern fit on are exactly those with it off (pattern_fit_max_side 0), where only the
// check runs (2-3 evaluations a view; 5-6 when Detect fitted again), and the corners are the
// check's: 0.023-0.034 px from the truth on these 15 x 7.5 px views, the edge fit alone 0.46-0.56 px.
TEST(SmallMarkers, SecondChanceCheckIsTheRefinement) {
  const int threads = cv::getNumThreads();
  cv::setNumThreads(0);  // every fit on this thread, where the count is kept
  const sim::Camera camera = test::RoverCamera();
  for (const double roll : {7.0, 97.0, 187.0, 277.0}) {
    const sim::Marker marker = FarMarker(10.0, 60.0, roll);
    const cv::Mat grey = RenderGrey(camera, {marker});
    const auto truth = sim::ProjectCorners(camera, marker);
    for (const bool fast : {true, false}) {
      DetectorConfig config = fast ? DetectorConfig() : FullSearch();
      config.tracking = false;
      size_t before = internal::PatternFitEvaluations();
      const auto refined = Detect(grey, Detector(config));
      const size_t with_fit = internal::PatternFitEvaluations() - before;
      config.pattern_fit_max_side = 0;
      before = internal::PatternFitEvaluations();
      const auto edges = Detect(grey, Detector(config));
      const size_t check_only = internal::PatternFitEvaluations() - before;
      const std::string view = "roll " + std::to_string(roll) + (fast ? " fast" : " full");
      ASSERT_EQ(refined.size(), 1u) << view;
      ASSERT_EQ(edges.size(), 1u) << view;
      EXPECT_GT(check_only, 0u) << view << ": read without the second chance";
      EXPECT_EQ(with_fit, check_only) << view;
      EXPECT_LT(MaxCornerError(refined[0], truth), 0.35) << view;
      std::printf("%s: %zu fit evaluations, corner error %.3f px (edge fit alone %.3f px)\n", view.c_str(), with_fit,
                  MaxCornerError(refined[0], truth), MaxCornerError(edges[0], truth));
    }
  }
  cv::setNumThreads(threads);
}

// tag36h11 markers of 13-18 px (cells of 1.6-2.3 px) under a camera's 0.8 px blur and 3 grey levels
// of noise, as bench's distant set has them. Two things kept the second chance from reading them: the
// contour of a blurred black square lies 0.5-1 px inside its edges (a third of a cell), and the
// estimate of a lone white cell among black ones lands near the threshold, which refused the whole
// reading; with 36 bits such cells can be left unknown. 48 views: 8 found before, 28 with unknown
// cells (26 without the reading on the edge-fitted quad; bench's distant set, bench_detect --misses:
// 27 of 60 before, 38 then, AprilTag 3 at decimate 1 42), 36 with up to 2 wrong cells corrected and
// the second polygon fit of small contours (distant set: 45 of 60).
TEST(SmallMarkers, BlurredTag36h11WithTwoPixelCellsIsRead) {
  const sim::Camera camera = test::RoverCamera();
  int found = 0, views = 0;
  for (const double range : {8.5, 10.0, 11.5}) {
    for (const double tilt : {0.0, 30.0}) {
      for (const double roll : {7.0, 97.0, 187.0, 277.0}) {
        for (const unsigned seed : {1u, 2u}) {
          const int id = (17 + 61 * views) % 587;
          const sim::Marker marker =
              sim::FacingCamera(id, 0.15, {0.1 * range, -0.05 * range, range}, tilt, 0.3 * tilt, roll);
          sim::RenderOptions options;
          options.dictionary = cv::aruco::DICT_APRILTAG_36h11;
          options.seed = seed + 10 * views;
          options.blur_sigma = 0.8;
          options.noise_sigma = 3.0;
          cv::Mat grey;
          PreprocessFrame(sim::RenderScene(camera, {marker}, options), grey);
          DetectorConfig config;
          config.dictionary = "DICT_APRILTAG_36h11";
          const auto tags = Detect(grey, Detector(config));
          ASSERT_LE(tags.size(), 1u) << range << " m, tilt " << tilt << ", roll " << roll;
          if (!tags.empty()) {
            EXPECT_EQ(tags[0].id, marker.id);
            EXPECT_LT(MaxCornerError(tags[0], sim::ProjectCorners(camera, marker)), 1.0) << range << " m";
          }
          found += static_cast<int>(tags.size());
          ++views;
        }
      }
    }
  }
  std::printf("blurred tag36h11 of 13-18 px: %d of %d found\n", found, views);
  EXPECT_GE(found, 32);
}

// A marker of `dictionary` with `cell` px cells on a white 120 px frame (top-left at 40, 40), with
// the data cells `flipped` (row by row) printed the other colour and a 0.6 px blur; `corners` get its
// black square.
cv::Mat MarkerWithFlippedCells(const cv::Ptr<cv::aruco::Dictionary>& dictionary, int id,
                               const std::vector<int>& flipped, int cell, std::array<cv::Point2f, 4>& corners) {
  const int bits = dictionary->markerSize, side = (bits + 2) * cell;
  cv::Mat marker;
  cv::aruco::drawMarker(dictionary, id, side, marker, 1);
  for (const int k : flipped) {
    cv::Mat square = marker(cv::Rect((k % bits + 1) * cell, (k / bits + 1) * cell, cell, cell));
    square = 255 - square;
  }
  cv::Mat grey(120, 120, CV_8UC1, cv::Scalar(255));
  marker.copyTo(grey(cv::Rect(40, 40, side, side)));
  cv::GaussianBlur(grey, grey, cv::Size(), 0.6);
  const float a = 39.5f, b = 39.5f + side;
  corners = {cv::Point2f(a, a), cv::Point2f(b, a), cv::Point2f(b, b), cv::Point2f(a, b)};
  return grey;
}

// The second chance corrects what a random pattern would rarely come that close to: up to 2 wrong
// cells of tag36h11's 36 (AprilTag 3's default), none of DICT_4X4_50's 16, whose 50 codes in 4
// rotations leave a random pattern 1 cell from some code 5 % of the time.
TEST(SmallMarkers, SecondChanceCorrectsTwoCellsOfTag36h11AndNoneOfFourByFour) {
  const auto tag36h11 = cv::aruco::getPredefinedDictionary(cv::aruco::DICT_APRILTAG_36h11);
  const auto four = cv::aruco::getPredefinedDictionary(cv::aruco::DICT_4X4_50);
  const std::vector<int> cells = {7, 22, 15, 28};
  for (size_t wrong = 0; wrong <= 3; ++wrong) {
    std::array<cv::Point2f, 4> corners;
    const std::vector<int> flipped(cells.begin(), cells.begin() + wrong);
    const cv::Mat grey = MarkerWithFlippedCells(tag36h11, 100, flipped, 3, corners);
    internal::SmallMarker read;
    const bool found = internal::DecodeSmall(grey, corners, *tag36h11, 1, false, read);
    EXPECT_EQ(found, wrong <= 2) << wrong << " wrong cells";
    if (found) {
      EXPECT_EQ(read.id, 100) << wrong << " wrong cells";
    }
  }
  for (size_t wrong = 0; wrong <= 1; ++wrong) {
    std::array<cv::Point2f, 4> corners;
    const std::vector<int> flipped(cells.begin(), cells.begin() + wrong);
    const cv::Mat grey = MarkerWithFlippedCells(four, kId, flipped, 4, corners);
    internal::SmallMarker read;
    EXPECT_EQ(internal::DecodeSmall(grey, corners, *four, 1, false, read), wrong == 0) << wrong << " wrong cells";
  }
}

// The quad whose side k (corner k to corner k + 1) lies inside[k] px inside the square `corners`.
std::array<cv::Point2f, 4> Inset(const std::array<cv::Point2f, 4>& corners, const std::array<float, 4>& inside) {
  const cv::Point2f centre = 0.25f * (corners[0] + corners[1] + corners[2] + corners[3]);
  std::array<cv::Point3f, 4> lines;  // (a, b, c): a x + b y + c = 0
  for (int k = 0; k < 4; ++k) {
    const cv::Point2f along = corners[(k + 1) % 4] - corners[k];
    cv::Point2f normal(-along.y, along.x);
    normal *= 1.0f / static_cast<float>(cv::norm(normal));
    if ((centre - corners[k]).dot(normal) < 0.0f) normal = -normal;
    const cv::Point2f on = corners[k] + normal * inside[k];
    lines[k] = cv::Point3f(normal.x, normal.y, -normal.dot(on));
  }
  std::array<cv::Point2f, 4> quad;
  for (int k = 0; k < 4; ++k) {  // corner k joins side k - 1 and side k
    const cv::Point3f p = lines[(k + 3) % 4].cross(lines[k]);
    quad[k] = cv::Point2f(p.x / p.z, p.y / p.z);
  }
  return quad;
}

// A 0.15 m tag36h11 marker at `range` (m) before the rover camera, tilted by `tilt` degrees and rolled
// by `roll`, with a third of the light and 0.6 of the contrast, the distant set's blur and noise, as
// bench's dim distant set renders it (noise seeded by `seed`); `truth` receives its corners.
cv::Mat DimTag36h11(int id, double range, double tilt, double roll, unsigned seed, std::array<cv::Point2f, 4>& truth) {
  const sim::Camera camera = test::RoverCamera();
  const sim::Marker marker = sim::FacingCamera(id, 0.15, {0.1 * range, -0.05 * range, range}, tilt, 0.3 * tilt, roll);
  sim::RenderOptions options;
  options.dictionary = cv::aruco::DICT_APRILTAG_36h11;
  options.seed = seed;
  options.blur_sigma = 0.8;
  options.noise_sigma = 3.0;
  options.brightness = 0.35;
  options.contrast = 0.6;
  cv::Mat grey;
  PreprocessFrame(sim::RenderScene(camera, {marker}, options), grey);
  truth = sim::ProjectCorners(camera, marker);
  return grey;
}

// How many of the framings `insets` (Inset) of dim tag36h11 markers (DimTag36h11) DecodeSmall reads,
// every reading the marker's own id. The markers: at each of `ranges` (m), facing the rover camera or
// tilted 30 degrees, in three rolls.
int DimTag36h11FramingsRead(const std::vector<double>& ranges, const std::vector<std::array<float, 4>>& insets) {
  const auto tag36h11 = cv::aruco::getPredefinedDictionary(cv::aruco::DICT_APRILTAG_36h11);
  int read = 0, views = 0;
  for (const double range : ranges) {
    for (const double tilt : {0.0, 30.0}) {
      for (const double roll : {20.0, 65.0, 130.0}) {
        const int id = (17 + 61 * views) % 587;
        ++views;
        std::array<cv::Point2f, 4> truth;
        const cv::Mat grey = DimTag36h11(id, range, tilt, roll, views, truth);
        for (size_t k = 0; k < insets.size(); ++k) {
          internal::SmallMarker small;
          if (!internal::DecodeSmall(grey, Inset(truth, insets[k]), *tag36h11, 1, false, small)) continue;
          EXPECT_EQ(small.id, id) << range << " m, tilt " << tilt << ", roll " << roll << ", framing " << k;
          ++read;
        }
      }
    }
  }
  return read;
}

// Dim tag36h11 markers of 10-15 px (1.3-1.9 px cells), each framed by its black square with every
// side 0.3-1.1 px inside, as a dim marker's contour lies: under 2.25 px per cell the other framings
// grow it in 0.2 px steps up to 0.9 px (kFineGrowPx). Measured: 33 of 90 framings read (28 when a
// first reading of a contrast just under kMinContrast was taken as flat, kMinMisframedContrast); none
// reads as another id.
TEST(SmallMarkers, DimTag36h11ReadFromContoursAFractionOfACellInside) {
  std::vector<std::array<float, 4>> insets;
  for (const float inside : {0.3f, 0.5f, 0.7f, 0.9f, 1.1f}) insets.push_back({inside, inside, inside, inside});
  const int read = DimTag36h11FramingsRead({10.0, 11.5, 13.0}, insets);
  std::printf("dim tag36h11 of 10-15 px framed 0.3-1.1 px inside: %d of 90 read\n", read);
  EXPECT_GE(read, 30);
}

// The same markers at 9-11.5 m (12-17 px), framed with one side 1.4-1.6 px inside and the others
// 0.2-0.6 px: the edge fit from that contour takes the border cells' inner edge for the square's on
// the far side, the one from the contour grown by 0.5 px (kEdgeStartGrowPx) reads. Measured: 67 of
// 108 framings read; 43 when a first reading of a contrast just under kMinContrast was taken as flat
// (kMinMisframedContrast).
TEST(SmallMarkers, DimTag36h11ReadFromContoursWithOneSideFarInside) {
  const int read = DimTag36h11FramingsRead(
      {9.0, 10.0, 11.5}, {{0.2f, 0.6f, 1.4f, 0.6f}, {0.6f, 0.2f, 0.6f, 1.4f}, {1.4f, 0.6f, 0.2f, 0.6f},
                          {0.6f, 1.4f, 0.6f, 0.2f}, {0.3f, 0.3f, 1.6f, 0.3f}, {1.6f, 0.3f, 0.3f, 0.3f}});
  std::printf("dim tag36h11 of 12-17 px framed with one side far inside: %d of 108 read\n", read);
  EXPECT_GE(read, 60);
}

// One small marker's contour traced twice (at two pyramid levels, or under two thresholds: quads too
// close to be two candidates) gets one second look. Decode reads such a group in the order its merge
// prefers (the finer level, then the bigger quad) and stops at the first read, so the pair costs what
// its first quad costs alone, in cell estimates and pattern-fit evaluations, and gives the same
// marker at the same corners. Dim tag36h11 markers of 12-15 px, which cv::aruco's reading misses, each
// framed 0.3 px and 0.6 px inside its black square.
TEST(SmallMarkers, MarkerTracedTwiceGetsOneSecondLook) {
  const auto tag36h11 = cv::aruco::getPredefinedDictionary(cv::aruco::DICT_APRILTAG_36h11);
  DetectorConfig config;
  config.dictionary = "DICT_APRILTAG_36h11";
  config.threads = 1;  // the counts are per thread
  const Detector detector(config);
  const auto quad = [](const std::array<cv::Point2f, 4>& truth, float inside) {
    internal::Quad q;
    q.corners = Inset(truth, {inside, inside, inside, inside});
    const std::vector<cv::Point2f> outline(q.corners.begin(), q.corners.end());
    q.area = static_cast<float>(cv::contourArea(outline));
    q.perimeter = static_cast<int>(cv::arcLength(outline, true));  // about its traced contour's length
    return q;
  };
  int views = 0, second_looks = 0;
  for (const double range : {9.0, 10.0, 11.0}) {
    for (const double roll : {20.0, 65.0, 130.0}) {
      const int id = (29 + 53 * views) % 587;
      ++views;
      std::array<cv::Point2f, 4> truth;
      const cv::Mat grey = DimTag36h11(id, range, 0.0, roll, views, truth);
      internal::Pyramid pyramid;
      pyramid.Build(grey);
      const internal::Quad outer = quad(truth, 0.3f), inner = quad(truth, 0.6f);
      const auto decode = [&](const std::vector<internal::Quad>& quads, size_t& estimates, size_t& evaluations) {
        const size_t cells_before = internal::SmallCellEstimates(), fit_before = internal::PatternFitEvaluations();
        const std::vector<internal::Found> found = internal::Decode(pyramid, quads, config, *tag36h11, *detector.parameters());
        estimates = internal::SmallCellEstimates() - cells_before;
        evaluations = internal::PatternFitEvaluations() - fit_before;
        return found;
      };
      size_t alone_estimates = 0, alone_evaluations = 0, pair_estimates = 0, pair_evaluations = 0;
      size_t inner_estimates = 0, inner_evaluations = 0;
      const std::vector<internal::Found> alone = decode({outer}, alone_estimates, alone_evaluations);
      const std::vector<internal::Found> inner_alone = decode({inner}, inner_estimates, inner_evaluations);
      // Only a marker the first quad's second look reads tells: one that cv::aruco's reading of either
      // quad reads (no cell estimate) is read before any second look.
      if (alone.size() != 1 || alone_estimates == 0 || (!inner_alone.empty() && inner_estimates == 0)) continue;
      ++second_looks;
      const std::vector<internal::Found> pair = decode({outer, inner}, pair_estimates, pair_evaluations);
      const std::string what = std::to_string(range) + " m, roll " + std::to_string(roll);
      EXPECT_EQ(alone[0].id, id) << what;
      ASSERT_EQ(pair.size(), 1u) << what;
      EXPECT_EQ(pair[0].id, id) << what;
      EXPECT_EQ(pair[0].corners, alone[0].corners) << what;
      EXPECT_EQ(pair_estimates, alone_estimates) << what;
      EXPECT_EQ(pair_evaluations, alone_evaluations) << what;
    }
  }
  std::printf("dim tag36h11 traced twice: %d of %d read by the first quad's second look\n", second_looks, views);
  EXPECT_GE(second_looks, 3);
}

// A low-contrast DICT_4X4_50 marker (ink 150, paper 200, 4 px cells, a 0.6 px blur) framed by a quad
// 1 px inside its black square, as a dim marker's contour lies: the first reading (that quad grown by
// 0.5 px, kGrowPx) is misframed. With its quiet zone (a cell of paper) on a surround a little brighter
// than the paper, or on a dark one, the other framings are tried and one reads it. The same pattern
// straight on the dark surround, far darker than its ink (3 contrasts below the cells' threshold: a
// lit patch in shadow, clutter), gets the first reading alone (kMaxMisframedQuiet): one cell estimate
// (more with the other framings, which read nothing there).
TEST(SmallMarkers, OtherFramingsOnlyAmidAMarkersSurroundings) {
  const auto four = cv::aruco::getPredefinedDictionary(cv::aruco::DICT_4X4_50);
  cv::Mat marker;
  cv::aruco::drawMarker(four, kId, 24, marker, 1);
  marker.convertTo(marker, CV_8U, 50.0 / 255.0, 150.0);
  const float a = 39.5f + 1.0f, b = 39.5f + 24.0f - 1.0f;
  const std::array<cv::Point2f, 4> shrunk = {cv::Point2f(a, a), cv::Point2f(b, a), cv::Point2f(b, b),
                                             cv::Point2f(a, b)};
  struct Case {
    int surround;
    bool quiet_zone;
  };
  for (const Case c : {Case{210, true}, Case{20, true}, Case{20, false}}) {
    cv::Mat grey(104, 104, CV_8UC1, cv::Scalar(c.surround));
    if (c.quiet_zone) grey(cv::Rect(36, 36, 32, 32)).setTo(cv::Scalar(200));
    marker.copyTo(grey(cv::Rect(40, 40, 24, 24)));
    cv::GaussianBlur(grey, grey, cv::Size(), 0.6);
    internal::SmallMarker read;
    const size_t before = internal::SmallCellEstimates();
    const bool found = internal::DecodeSmall(grey, shrunk, *four, 1, false, read);
    const size_t estimates = internal::SmallCellEstimates() - before;
    const std::string what = "surround " + std::to_string(c.surround) + (c.quiet_zone ? " with" : " without") +
                             " a quiet zone";
    if (c.quiet_zone) {
      EXPECT_TRUE(found) << what;
      EXPECT_EQ(read.id, kId) << what;
      EXPECT_GT(estimates, 1u) << what;
    } else {
      EXPECT_FALSE(found) << what;
      EXPECT_EQ(estimates, 1u) << what;
    }
  }
}

// The second chance accepts codes with a whole border only: textured frames without a
// marker give nothing, on either path (640x480, the rover camera's field of view, to keep the
// 200 renders quick).
TEST(SmallMarkers, NoMarkerFoundOnMarkerFreeTexturedFrames) {
  const sim::Camera camera = sim::MakeCamera({640, 480}, 65.0);
  const Detector fast, full(FullSearch());
  int fast_tags = 0, full_tags = 0;
  for (unsigned seed = 1; seed <= 200; ++seed) {
    const cv::Mat grey = RenderGrey(camera, {}, seed);
    fast.ResetTracking();
    fast_tags += static_cast<int>(Detect(grey, fast).size());
    full_tags += static_cast<int>(Detect(grey, full).size());
  }
  EXPECT_EQ(fast_tags, 0);
  EXPECT_EQ(full_tags, 0);
}

// Found by fuzz_core (regress_pattern_fit_slow): the full search gave the second chance to every
// rejected candidate, 75 of them 1-3 px quads of equalized noise on an 80x80 frame; a 1280x720 frame
// of 12 px noise blocks gave 1576 (146 ms). Unreadable quads are skipped, and at most
// kMaxSmallCandidates of the rest, the biggest, are tried, in cv::aruco's order.
TEST(SmallMarkers, SecondChanceWorkPerFrameIsBounded) {
  const auto square = [](float side) {
    return std::vector<cv::Point2f>{{10, 10}, {10 + side, 10}, {10 + side, 10 + side}, {10, 10 + side}};
  };
  const int cells = 6;  // a 4x4 marker and its border
  std::vector<std::vector<cv::Point2f>> rejected;
  for (int i = 0; i < 1000; ++i) rejected.push_back(square(1.0f + static_cast<float>((i * 7) % 40)));
  const std::vector<size_t> tried = internal::SmallCandidates(rejected, cells);
  ASSERT_EQ(tried.size(), internal::kMaxSmallCandidates);
  EXPECT_TRUE(std::is_sorted(tried.begin(), tried.end()));
  float smallest_tried = internal::kSmallCandidateMaxSide;
  for (const size_t i : tried) smallest_tried = std::min(smallest_tried, rejected[i][1].x - rejected[i][0].x);
  for (size_t i = 0; i < rejected.size(); ++i) {
    const float side = rejected[i][1].x - rejected[i][0].x;
    const bool was_tried = std::binary_search(tried.begin(), tried.end(), i);
    if (side < cells || side >= internal::kSmallCandidateMaxSide) {
      EXPECT_FALSE(was_tried) << side;
    } else if (side > smallest_tried) {
      EXPECT_TRUE(was_tried) << side;  // the biggest are the ones tried
    }
  }
  // Under the bound, every readable small candidate, in order.
  rejected = {square(3.0f), square(6.0f), square(29.0f), square(30.0f), square(12.0f), {{1, 1}, {2, 2}}};
  EXPECT_EQ(internal::SmallCandidates(rejected, cells), (std::vector<size_t>{1, 2, 4}));
}

// Real photos read with dictionaries they do not use, shrunk so their markers become small
// candidates: every detection is false. The second chance must not add any to what cv::aruco reports
// (a review found 27 on the full search before its quiet-zone and pattern checks); the fast path's
// multi-scale search reads a few more contours than cv::aruco (25 before the second chance existed).
TEST(SmallMarkers, NoExtraFalsePositivesOnPhotosWithWrongDictionaries) {
  int plain = 0, fast = 0, full = 0;
  for (const std::string file : {"opencv_tutorial/singlemarkersoriginal.jpg", "opencv_tutorial/choriginal.jpg",
                                 "opencv_tutorial/chocclusion_original.jpg", "ubiquity_fiducials/tag_01_d7_14cm.png",
                                 "ubiquity_fiducials/tag_245-246_d7_14cm.png"}) {
    const cv::Mat photo = test::LoadGrey(file);
    for (double scale : {1.0, 0.8, 0.6, 0.5, 0.4, 0.3, 0.22}) {
      cv::Mat grey;
      cv::resize(photo, grey, cv::Size(), scale, scale, cv::INTER_AREA);
      for (const std::string name :
           {"DICT_4X4_1000", "DICT_4X4_250", "DICT_ARUCO_ORIGINAL", "DICT_APRILTAG_36h11", "DICT_7X7_1000"}) {
        DetectorConfig fast_config;
        fast_config.dictionary = name;
        fast_config.tracking = false;
        DetectorConfig full_config = fast_config;
        full_config.fast_path = false;
        std::vector<std::vector<cv::Point2f>> corners;
        std::vector<int> ids;
        cv::aruco::detectMarkers(grey, cv::aruco::getPredefinedDictionary(DictionaryFromName(name)), corners, ids,
                                 cv::aruco::DetectorParameters::create());
        plain += static_cast<int>(ids.size());
        fast += static_cast<int>(Detect(grey, Detector(fast_config)).size());
        full += static_cast<int>(Detect(grey, Detector(full_config)).size());
      }
    }
  }
  std::printf("wrong-dictionary detections: cv::aruco %d, fast path %d, full search %d\n", plain, fast, full);
  EXPECT_LE(full, plain);
  EXPECT_LE(fast, 25);
}

}  // namespace
}  // namespace arucotag

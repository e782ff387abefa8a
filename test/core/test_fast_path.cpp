// The fast path (DetectorConfig::fast_path, on by default) against the full search it replaces
// (cv::aruco::detectMarkers with the same configuration): same ids and corners on the real photos,
// and tracking that restricts where a frame is searched, not what is found there.
#include <algorithm>
#include <cmath>
#include <cstdio>
#include <map>
#include <set>
#include <string>

#include <gtest/gtest.h>
#include <opencv2/imgcodecs.hpp>

#include <opencv2/imgproc.hpp>

#include "candidates.hpp"
#include "contours.hpp"
#include "identify.hpp"
#include "refine_edges.hpp"
#include "scene.hpp"

namespace arucotag {
namespace {

std::multiset<int> Ids(const std::vector<ArucoTag>& tags) {
  std::multiset<int> ids;
  for (const auto& t : tags) ids.insert(t.id);
  return ids;
}

// The same markers, corners to the bit, in the same order.
bool SameTags(const std::vector<ArucoTag>& a, const std::vector<ArucoTag>& b) {
  if (a.size() != b.size()) return false;
  for (size_t i = 0; i < a.size(); ++i) {
    if (a[i].id != b[i].id || a[i].corners != b[i].corners) return false;
  }
  return true;
}

const ArucoTag* Find(const std::vector<ArucoTag>& tags, int id) {
  const auto it = std::find_if(tags.begin(), tags.end(), [id](const ArucoTag& t) { return t.id == id; });
  return it == tags.end() ? nullptr : &*it;
}

double MaxCornerDifference(const ArucoTag& a, const ArucoTag& b) {
  double worst = 0.0;
  for (int i = 0; i < 4; ++i) worst = std::max(worst, cv::norm(cv::Point2d(a.corners[i]) - cv::Point2d(b.corners[i])));
  return worst;
}

// Every marker the full search reports, with its corners within `tolerance` px; nothing else.
void ExpectSameAsFullSearch(const std::vector<ArucoTag>& fast, const std::vector<ArucoTag>& full, double tolerance,
                            const std::string& what) {
  ASSERT_EQ(Ids(fast), Ids(full)) << what;
  for (const auto& f : full) {
    const ArucoTag* q = Find(fast, f.id);
    ASSERT_NE(q, nullptr) << what << " id " << f.id;
    EXPECT_LE(MaxCornerDifference(*q, f), tolerance) << what << " id " << f.id;
  }
}

struct Photo {
  std::string file, dictionary;
  size_t markers;
};

const std::vector<Photo> kPhotos = {
    {"opencv_tutorial/singlemarkersoriginal.jpg", "DICT_6X6_250", 6},
    {"opencv_tutorial/choriginal.jpg", "DICT_6X6_250", 17},
    {"opencv_tutorial/chocclusion_original.jpg", "DICT_6X6_250", 13},
    {"ubiquity_fiducials/tag_01_d7_14cm.png", "DICT_5X5_1000", 1},
    {"ubiquity_fiducials/tag_245-246_d7_14cm.png", "DICT_5X5_1000", 2},
};

// The level-0 search's quads of a whole grey frame (cv::aruco's default candidate filters).
std::vector<internal::Quad> LevelZeroQuads(const cv::Mat& grey) {
  const DetectorConfig config;
  internal::Pyramid pyramid;
  pyramid.Build(grey);
  std::vector<internal::Quad> quads;
  internal::RunTasks(pyramid, {internal::MakeTask(config, grey.size(), 0, cv::Rect(cv::Point(0, 0), grey.size()))},
                     config, quads);
  return quads;
}

// The quad of `quads` whose corners are all within `tolerance` px of `square`'s (any start), or null.
const internal::Quad* QuadAt(const std::vector<internal::Quad>& quads, const std::array<cv::Point2f, 4>& square,
                             double tolerance) {
  for (const auto& q : quads) {
    for (int shift = 0; shift < 4; ++shift) {
      bool near = true;
      for (int k = 0; k < 4; ++k) near = near && cv::norm(q.corners[(k + shift) % 4] - square[k]) <= tolerance;
      if (near) return &q;
    }
  }
  return nullptr;
}

// A small marker's black border cut by the threshold (a dim frame, see candidates.cpp's
// kHullContourPoints): the outline runs through the gap into the marker, so no polygon fit of it is
// a quad, and the search takes its convex hull's where the binary image looks like a marker's around
// it (a dark ring, light outside and inside). Drawn here as 14-18 px square rings, 2 px wide, with
// a 2 px gap in one side, on a bright background: each gives a quad at its outer corners (within a
// pixel: the contour runs through the centres of the ring's outer pixels). Round rings broken the
// same way, and three sides of a square drawn one pixel wide, give none.
TEST(FastPath, BrokenSquareBorderGivesItsHullsQuad) {
  cv::Mat grey(240, 320, CV_8UC1, cv::Scalar(200));
  std::vector<std::array<cv::Point2f, 4>> squares;
  for (int k = 0; k < 3; ++k) {
    const int side = 14 + 2 * k, x = 30 + 90 * k, y = 40;
    const cv::Rect outer(x, y, side, side);
    cv::rectangle(grey, outer, cv::Scalar(40), cv::FILLED);
    cv::rectangle(grey, cv::Rect(x + 2, y + 2, side - 4, side - 4), cv::Scalar(200), cv::FILLED);
    // The gap: in the right side for the first, the bottom for the second, the left for the third.
    const cv::Rect gaps[] = {{x + side - 2, y + side / 2 - 1, 2, 2}, {x + side / 2 - 1, y + side - 2, 2, 2},
                             {x, y + side / 2 - 1, 2, 2}};
    cv::rectangle(grey, gaps[k], cv::Scalar(200), cv::FILLED);
    const float x1 = static_cast<float>(x + side - 1), y1 = static_cast<float>(y + side - 1);
    squares.push_back({cv::Point2f(x, y), cv::Point2f(x1, y), cv::Point2f(x1, y1), cv::Point2f(x, y1)});
  }
  // Below them: round rings broken the same way (their hulls are round), and three sides of a square
  // drawn one pixel wide (its hull's quad has no dark border ring).
  for (int k = 0; k < 3; ++k) {
    const cv::Point centre(40 + 90 * k, 160);
    cv::circle(grey, centre, 7 + 2 * k, cv::Scalar(40), 2);
    cv::rectangle(grey, cv::Rect(centre.x + 6 + 2 * k - 1, centre.y - 1, 4, 2), cv::Scalar(200), cv::FILLED);
  }
  cv::line(grey, cv::Point(290, 150), cv::Point(306, 150), cv::Scalar(40), 1);
  cv::line(grey, cv::Point(290, 150), cv::Point(290, 166), cv::Scalar(40), 1);
  cv::line(grey, cv::Point(306, 150), cv::Point(306, 166), cv::Scalar(40), 1);

  const std::vector<internal::Quad> quads = LevelZeroQuads(grey);
  for (size_t k = 0; k < squares.size(); ++k) {
    EXPECT_NE(QuadAt(quads, squares[k], 1.0), nullptr) << "ring " << k;
  }
  for (const auto& q : quads) {
    const cv::Point2f centre = (q.corners[0] + q.corners[1] + q.corners[2] + q.corners[3]) * 0.25f;
    EXPECT_LT(centre.y, 120.0f) << "a quad on a round ring or on the lines, centre " << centre;
  }
}

// A hole (light region inside a dark one) whose box lies inside an earlier quad's is that quad's
// inside -- a marker's white cells, the light square within a frame -- never a marker of its own
// (markers do not nest), so the search lists no quad for it; a hole inside dark clutter that made no
// quad is still listed (a small blurred marker whose own outline failed can be read from the hole
// around it: one on the 1080p/20 bench set). Drawn: two 3 px dark square frames round 20 px light
// squares, the second with a 3 px line leaving it (its outer border is then no quad).
TEST(FastPath, HolesInsideAQuadAreNotListed) {
  cv::Mat grey(240, 320, CV_8UC1, cv::Scalar(200));
  const cv::Rect frames[] = {{40, 60, 26, 26}, {180, 60, 26, 26}};
  for (const cv::Rect& f : frames) {
    cv::rectangle(grey, f, cv::Scalar(40), cv::FILLED);
    cv::rectangle(grey, cv::Rect(f.x + 3, f.y + 3, f.width - 6, f.height - 6), cv::Scalar(200), cv::FILLED);
  }
  cv::rectangle(grey, cv::Rect(frames[1].x + frames[1].width, frames[1].y + 11, 60, 3), cv::Scalar(40), cv::FILLED);
  // The outer border runs through the frame's outer pixels, a hole's through the inner ones.
  const auto square = [](int x0, int y0, int x1, int y1) {
    return std::array<cv::Point2f, 4>{cv::Point2f(x0, y0), cv::Point2f(x1, y0), cv::Point2f(x1, y1), cv::Point2f(x0, y1)};
  };
  const std::vector<internal::Quad> quads = LevelZeroQuads(grey);
  const cv::Rect& a = frames[0];
  const cv::Rect& b = frames[1];
  EXPECT_NE(QuadAt(quads, square(a.x, a.y, a.x + a.width - 1, a.y + a.height - 1), 1.0), nullptr);
  EXPECT_EQ(QuadAt(quads, square(a.x + 2, a.y + 2, a.x + a.width - 3, a.y + a.height - 3), 1.0), nullptr);
  EXPECT_NE(QuadAt(quads, square(b.x + 2, b.y + 2, b.x + b.width - 3, b.y + b.height - 3), 1.5), nullptr);
  EXPECT_EQ(quads.size(), 2u);
}

// The canonical image's sampling, four pixels at a time, against warpPerspective's INTER_NEAREST
// arithmetic one pixel at a time (double, cvRound, 1 / 0 taken as 0): the same pixel for every
// canonical pixel of random candidates in and around the frame, of rows that end exactly half-way
// between pixels (cvRound's ties), of w through 0 and of coordinates past int's range.
TEST(FastPath, CanonicalSamplingMatchesWarpPerspectivesRounding) {
  const int cols = 640, rows = 480, step = 704;
  const auto reference = [&](double x0, double y0, double w0, double dx, double dy, double dw, int x) {
    double w = w0 + dw * x;
    w = w ? 1.0 / w : 0.0;
    const int sx = cvRound((x0 + dx * x) * w), sy = cvRound((y0 + dy * x) * w);
    return unsigned(sx) < unsigned(cols) && unsigned(sy) < unsigned(rows) ? sy * step + sx : -1;
  };
  cv::RNG rng(14);
  int compared = 0, inside = 0, ties = 0;
  for (int trial = 0; trial < 20000; ++trial) {
    const int size = 1 + trial % 40;
    double x0 = rng.uniform(-100.0, 740.0), y0 = rng.uniform(-100.0, 580.0), w0 = rng.uniform(0.5, 1.5);
    double dx = rng.uniform(-3.0, 3.0), dy = rng.uniform(-3.0, 3.0), dw = rng.uniform(-0.01, 0.01);
    switch (trial % 5) {
      case 0:  // half-pixel steps from a half-pixel start: every other pixel a tie
        x0 = std::floor(x0) + 0.5, y0 = std::floor(y0) + 0.5, w0 = 1.0, dw = 0.0, dx = 0.5, dy = -0.5;
        break;
      case 1:  // w crosses 0 inside the row
        w0 = 0.02 * size, dw = -0.04;
        break;
      case 2:  // far past int's range
        x0 *= 1e12, y0 *= -1e9;
        break;
      default:
        break;
    }
    int offsets[44];
    internal::CanonicalRowSources(x0, y0, w0, dx, dy, dw, size, cols, rows, step, offsets);
    for (int x = 0; x < size; ++x) {
      const int expected = reference(x0, y0, w0, dx, dy, dw, x);
      ASSERT_EQ(offsets[x], expected) << "trial " << trial << " x " << x;
      ++compared;
      inside += expected >= 0;
      const double fx = (x0 + dx * x) / (w0 + dw * x);
      ties += expected >= 0 && fx - std::floor(fx) == 0.5;
    }
  }
  std::printf("%d canonical pixels, %d inside the frame, %d on a tie\n", compared, inside, ties);
  EXPECT_GT(inside, compared / 4);
  EXPECT_GT(ties, 1000);
}

// The codes cached for a dictionary are made again when its bytes change where they are: a
// dictionary edited in place (two markers' codes swapped, the same bytesList buffer) reads by its new
// codes, not by those the cache kept for that address.
TEST(FastPath, CodeCacheFollowsADictionaryChangedInPlace) {
  cv::aruco::Dictionary dictionary = *cv::aruco::getPredefinedDictionary(cv::aruco::DICT_4X4_50);
  dictionary.bytesList = dictionary.bytesList.clone();
  const uchar* const buffer = dictionary.bytesList.data;
  cv::Mat marker;
  cv::aruco::drawMarker(cv::makePtr<cv::aruco::Dictionary>(dictionary), 3, 120, marker);
  cv::Mat grey(200, 200, CV_8UC1, cv::Scalar(255));
  marker.copyTo(grey(cv::Rect(40, 40, 120, 120)));
  const std::array<cv::Point2f, 4> corners = {cv::Point2f(39.5f, 39.5f), cv::Point2f(159.5f, 39.5f),
                                              cv::Point2f(159.5f, 159.5f), cv::Point2f(39.5f, 159.5f)};
  const auto params = cv::aruco::DetectorParameters::create();
  int id = -1, rotation = -1;
  ASSERT_TRUE(internal::Identify(grey, corners, dictionary, *params, id, rotation));
  EXPECT_EQ(id, 3);
  EXPECT_EQ(rotation, 0);
  // Markers 3 and 7 trade codes in place: the drawing of 3 is now marker 7's code.
  cv::Mat three = dictionary.bytesList.row(3).clone();
  dictionary.bytesList.row(7).copyTo(dictionary.bytesList.row(3));
  three.copyTo(dictionary.bytesList.row(7));
  ASSERT_EQ(dictionary.bytesList.data, buffer);
  ASSERT_TRUE(internal::Identify(grey, corners, dictionary, *params, id, rotation));
  EXPECT_EQ(id, 7);
  EXPECT_EQ(rotation, 0);
}

// The pyramid's halving (its own 2x2 average where the CPU has AVX2) against cv::resize's INTER_AREA,
// pixel for pixel: random images of even and odd sizes, widths either side of its 32-pixel steps, every
// pixel sum's remainder (the rounding), regions of a bigger image in and out, and the sizes the
// benchmark's frames halve through.
TEST(FastPath, HalvingMatchesInterArea) {
  cv::RNG rng(46);
  const cv::Size sizes[] = {{2, 2},    {3, 5},     {30, 2},    {62, 4},    {64, 6},     {66, 8},    {127, 33},
                            {130, 34}, {320, 240}, {641, 480}, {640, 481}, {960, 540}, {1920, 1080}};
  int pixels = 0;
  for (const cv::Size& size : sizes) {
    for (int trial = 0; trial < 3; ++trial) {
      cv::Mat src(size, CV_8UC1);
      rng.fill(src, cv::RNG::UNIFORM, 0, 256);
      if (trial == 1) src.setTo(255);  // the largest sums
      cv::Mat expected, halved;
      cv::resize(src, expected, cv::Size(size.width / 2, size.height / 2), 0, 0, cv::INTER_AREA);
      internal::HalveArea(src, halved);
      ASSERT_EQ(halved.size(), expected.size()) << size;
      ASSERT_EQ(cv::norm(halved, expected, cv::NORM_INF), 0.0) << size << " trial " << trial;
      pixels += static_cast<int>(expected.total());
    }
  }
  // A region of a bigger image in, into a region of another: only that region is written.
  cv::Mat big(200, 300, CV_8UC1), out(120, 160, CV_8UC1, cv::Scalar(7));
  rng.fill(big, cv::RNG::UNIFORM, 0, 256);
  const cv::Rect from(10, 20, 98, 64), to(30, 40, 49, 32);
  cv::Mat region = out(to);
  internal::HalveArea(big(from), region);
  cv::Mat expected;
  cv::resize(big(from), expected, to.size(), 0, 0, cv::INTER_AREA);
  EXPECT_EQ(region.data, out.ptr<uchar>(to.y) + to.x);
  EXPECT_EQ(cv::norm(out(to), expected, cv::NORM_INF), 0.0);
  cv::Mat outside = out.clone();
  outside(to).setTo(7);
  EXPECT_EQ(cv::countNonZero(outside != 7), 0);
  std::printf("%d halved pixels compared\n", pixels);
}

// The candidate search's threshold is cv::adaptiveThreshold's, pixel for pixel, on the windows and
// constants it takes 16-bit box sums for and on those it hands to OpenCV: real photos, noise, flat
// images at both ends of the grey range (the largest sums and the smallest), odd sizes, a region of a
// bigger image.
TEST(FastPath, ThresholdMatchesAdaptiveThreshold) {
  std::vector<std::pair<std::string, cv::Mat>> images;
  for (const char* name : {"opencv_tutorial/singlemarkersoriginal.jpg", "ubiquity_fiducials/tag_245-246_d7_14cm.png"}) {
    images.emplace_back(name, cv::imread(std::string(ARUCOTAG_TEST_DATA) + "/" + name, cv::IMREAD_GRAYSCALE));
    ASSERT_FALSE(images.back().second.empty()) << name;
  }
  cv::RNG rng(47);
  for (const cv::Size& size : {cv::Size(641, 480), cv::Size(13, 9), cv::Size(5, 40)}) {
    cv::Mat noise(size, CV_8UC1);
    rng.fill(noise, cv::RNG::UNIFORM, 0, 256);
    images.emplace_back("noise", noise);
  }
  images.emplace_back("black", cv::Mat(60, 70, CV_8UC1, cv::Scalar(0)));
  images.emplace_back("white", cv::Mat(60, 70, CV_8UC1, cv::Scalar(255)));
  cv::Mat big(300, 400, CV_8UC1);
  rng.fill(big, cv::RNG::UNIFORM, 0, 256);
  images.emplace_back("region", big(cv::Rect(17, 31, 201, 150)));
  int pixels = 0;
  for (const auto& [name, grey] : images) {
    for (int window : {3, 5, 7, 11, 23}) {
      for (double constant : {0.0, 3.0, 7.0, 7.9, 15.0, 23.0, -2.0}) {
        cv::Mat binary, expected;
        cv::adaptiveThreshold(grey, binary, internal::kForeground, cv::ADAPTIVE_THRESH_MEAN_C, cv::THRESH_BINARY_INV,
                              window, constant);
        cv::copyMakeBorder(binary, expected, 1, 1, 1, 1, cv::BORDER_CONSTANT, cv::Scalar(0));
        cv::Mat out;
        internal::Threshold(grey, window, constant, out);
        ASSERT_EQ(out.size(), expected.size()) << name;
        ASSERT_EQ(cv::norm(out, expected, cv::NORM_INF), 0.0)
            << name << " window " << window << " constant " << constant;
        pixels += static_cast<int>(grey.total());
      }
    }
  }
  std::printf("%d thresholded pixels compared\n", pixels);
}

// The default refinement (edge fit) and cv::aruco's sub-pixel one, both supported by the fast path.
TEST(FastPath, RealPhotosSameIdsAndCornersAsTheFullSearch) {
  for (const auto refinement : {DetectorConfig().corner_refinement, CornerRefinement::kSubpix}) {
    for (const auto& photo : kPhotos) {
      DetectorConfig config;
      config.dictionary = photo.dictionary;
      config.corner_refinement = refinement;
      config.tracking = false;
      DetectorConfig reference = config;
      reference.fast_path = false;
      const cv::Mat grey = test::LoadGrey(photo.file);
      const auto fast = Detect(grey, Detector(config));
      const auto full = Detect(grey, Detector(reference));
      EXPECT_EQ(full.size(), photo.markers) << photo.file;
      ExpectSameAsFullSearch(fast, full, 0.1, photo.file + " refinement " + std::to_string(static_cast<int>(refinement)));
    }
  }
}

// A static rover camera watching three markers; `extra` joins from `appear` on.
struct Sequence {
  sim::Camera camera = test::RoverCamera();
  std::vector<sim::Marker> markers = {sim::FacingCamera(3, 0.15, {-0.9, -0.2, 3.0}, 20.0, 0.0, 10.0),
                                      sim::FacingCamera(17, 0.15, {0.8, 0.25, 4.0}, -30.0, 10.0, 100.0),
                                      sim::FacingCamera(29, 0.15, {0.1, -0.35, 2.5}, 0.0, -25.0, 200.0)};

  cv::Mat Frame(int k, const sim::Marker& extra, int appear) const {
    std::vector<sim::Marker> all = markers;
    if (k >= appear) all.push_back(extra);
    sim::RenderOptions options;
    options.seed = 5;  // the same clutter every frame: one scene
    options.noise_sigma = 2.0;
    options.blur_sigma = 0.5;
    return test::RenderGrey(camera, all, options);
  }
};

// The fast path starts the edge fit from its own full-resolution contour when that fit settles (one
// more pass would move no corner by over kEdgeFitSettledPx) and from cv::aruco's corners otherwise: a
// settled fit has reached its fixed point, so two starts a pixel apart end at the same corners, within
// the 0.1 px the fast path keeps to the full search.
TEST(FastPath, SettledEdgeFitEndsWhereverItStarts) {
  const sim::Camera camera = test::RoverCamera();
  int views = 0, settled = 0;
  double worst = 0.0;
  for (const double range : {1.5, 3.0, 5.0}) {
    for (const double yaw : {-45.0, 0.0, 30.0}) {
      for (const double roll : {10.0, 55.0}) {
        const sim::Marker marker = sim::FacingCamera(7, 0.15, {0.2, -0.1, range}, yaw, 10.0, roll);
        sim::RenderOptions options;
        options.blur_sigma = 0.8;
        options.noise_sigma = 2.0;
        options.seed = static_cast<unsigned>(views + 1);
        cv::Mat grey;
        PreprocessFrame(sim::RenderScene(camera, {marker}, options), grey);
        const auto truth = sim::ProjectCorners(camera, marker);
        std::array<cv::Point2f, 4> a = truth, b = truth;
        const cv::Point2f shift_a[4] = {{0.8f, -0.5f}, {-0.6f, 0.7f}, {0.5f, 0.9f}, {-0.9f, -0.4f}};
        const cv::Point2f shift_b[4] = {{-0.7f, 0.6f}, {0.9f, -0.3f}, {-0.4f, -0.8f}, {0.6f, 0.5f}};
        for (int i = 0; i < 4; ++i) {
          a[i] += shift_a[i];
          b[i] += shift_b[i];
        }
        ++views;
        const bool settled_a = internal::RefineCornersOnEdgesSettled(grey, a, 6, internal::kEdgeFitSettledPx);
        const bool settled_b = internal::RefineCornersOnEdgesSettled(grey, b, 6, internal::kEdgeFitSettledPx);
        if (!settled_a || !settled_b) continue;
        ++settled;
        for (int i = 0; i < 4; ++i) worst = std::max(worst, static_cast<double>(cv::norm(a[i] - b[i])));
      }
    }
  }
  std::printf("%d of %d views settled from both starts; their corners at most %.3f px apart\n", settled, views,
              worst);
  EXPECT_GE(settled, views / 2) << "too few settled fits: the test would prove little";
  EXPECT_LE(worst, 0.1);
}

// A marker that appears inside the frame (not from an edge) while the others are tracked is found
// within full_search_interval frames; every other frame gives the full search's ids and corners.
TEST(FastPath, NewMarkerFoundWithinTheFullSearchInterval) {
  const Sequence sequence;
  // About 22 px wide at 7 m: below the size the coarse level sees on every frame.
  const sim::Marker small = sim::FacingCamera(41, 0.15, {0.3, 0.6, 7.0}, 15.0, 0.0, 30.0);
  const int appear = 3;
  const Detector detector;  // defaults: fast path, tracking
  DetectorConfig full_config;
  full_config.fast_path = false;
  const Detector full(full_config);
  const int interval = detector.config().full_search_interval;
  int found_at = -1;
  for (int k = 0; k < appear + interval + 1; ++k) {
    const cv::Mat grey = sequence.Frame(k, small, appear);
    const auto tags = Detect(grey, detector);
    const auto reference = Detect(grey, full);
    ASSERT_EQ(Find(reference, 41) != nullptr, k >= appear) << "frame " << k << ": the scene is not what the test expects";
    if (found_at < 0 && Find(tags, 41)) found_at = k;
    // Apart from the newcomer before it is found: exactly the full search's answer.
    std::vector<ArucoTag> expected = reference;
    if (found_at < 0) {
      expected.erase(std::remove_if(expected.begin(), expected.end(), [](const ArucoTag& t) { return t.id == 41; }),
                     expected.end());
    }
    // Tracked markers' fits start from last frame's and the full search's from cold; each ends with
    // a step it does not confirm (kCarriedLastStep, kColdLastStep), so they agree to about a
    // hundredth of a pixel (at most 0.012 px here), not exactly.
    ExpectSameAsFullSearch(tags, expected, 0.02, "frame " + std::to_string(k));
  }
  EXPECT_GE(detector.tracking_stats().tracked_frames, static_cast<unsigned long long>(appear))
      << "tracking never engaged: the test would prove nothing";
  ASSERT_GE(found_at, appear) << "marker 41 never found";
  std::printf("new marker found %d frame(s) after it appeared (bound %d)\n", found_at - appear, interval - 1);
  EXPECT_LT(found_at, appear + interval) << "found " << found_at - appear << " frames after it appeared";
}

// A large marker that appears away from the image edges is beyond the entry band's reach too: it
// is found by the next full scan, within full_search_interval frames.
TEST(FastPath, NewLargeMarkerFoundWithinTheFullSearchInterval) {
  const Sequence sequence;
  const sim::Marker large = sim::FacingCamera(44, 0.15, {0.35, 0.05, 1.6}, 0.0, 20.0, 0.0);  // about 95 px
  const Detector detector;
  const int interval = detector.config().full_search_interval;
  const int appear = 2;
  int found_at = -1;
  for (int k = 0; k < appear + interval; ++k) {
    const auto tags = Detect(sequence.Frame(k, large, appear), detector);
    if (k < appear) {
      EXPECT_EQ(Find(tags, 44), nullptr) << "frame " << k;
    }
    if (found_at < 0 && Find(tags, 44)) found_at = k;
  }
  EXPECT_GE(detector.tracking_stats().tracked_frames, 2u);
  ASSERT_GE(found_at, appear) << "marker 44 never found";
  EXPECT_LT(found_at, appear + interval) << "found " << found_at - appear << " frames after it appeared";
}

// Video mode's budget: a tracked frame reads its markers where they are predicted and searches
// nothing else while the camera stands still (no region to search, no edge the scene moves in
// from); the whole frame is searched on the first frame and then once every full_search_interval
// frames; every frame reports what the full search reports.
TEST(FastPath, TrackedFramesReadMarkersWithoutASearchAndScanOnABudget) {
  const Sequence sequence;
  const sim::Marker none = sim::FacingCamera(0, 0.15, {0.0, 0.0, -5.0});  // behind the camera: never seen
  DetectorConfig config;
  config.full_search_interval = 5;
  const Detector detector(config);
  DetectorConfig full_config;
  full_config.fast_path = false;
  const Detector full(full_config);
  const int frames = 2 * config.full_search_interval + 2;
  unsigned long long one_full_search = 0;
  for (int k = 0; k < frames; ++k) {
    const cv::Mat grey = sequence.Frame(k, none, 1000);
    const auto tags = Detect(grey, detector);
    ExpectSameAsFullSearch(tags, Detect(grey, full), 0.01, "frame " + std::to_string(k));
    if (k == 0) one_full_search = detector.tracking_stats().searched_pixels;
  }
  ASSERT_GT(one_full_search, 0u);
  const auto stats = detector.tracking_stats();
  // Frames 0, 5 and 10 (k = 0 and every full_search_interval after it).
  const unsigned long long scans = 1 + (frames - 1) / config.full_search_interval;
  EXPECT_EQ(stats.full_searches, scans);
  EXPECT_EQ(stats.tracked_frames, frames - scans);
  EXPECT_EQ(stats.read_at_prediction, 3u * (frames - 1)) << "every tracked marker read where predicted";
  EXPECT_EQ(stats.searched_pixels, scans * one_full_search) << "tracked frames searched pixels";
}

// Another scene after a tracked one (a cut, or unrelated images through one Detector) is searched
// whole on its first frame.
TEST(FastPath, UnrelatedImageAfterTrackedFramesIsSearchedWhole) {
  const Sequence sequence;
  const sim::Marker none = sim::FacingCamera(0, 0.15, {0.0, 0.0, -5.0});  // behind the camera: never seen
  const Detector detector;
  for (int k = 0; k < 3; ++k) Detect(sequence.Frame(k, none, 100), detector);

  const sim::Camera camera = test::RoverCamera();
  const std::vector<sim::Marker> others = {sim::FacingCamera(8, 0.15, {-0.5, 0.1, 5.0}),
                                           sim::FacingCamera(12, 0.15, {0.6, -0.3, 6.5}, 25.0)};
  sim::RenderOptions options;
  options.seed = 9;
  cv::Mat grey;
  PreprocessFrame(sim::RenderScene(camera, others, options), grey);
  DetectorConfig cold_config;
  cold_config.tracking = false;
  ExpectSameAsFullSearch(Detect(grey, detector), Detect(grey, Detector(cold_config)), 0.0, "first frame after the cut");
  EXPECT_EQ(Ids(Detect(grey, Detector(cold_config))), (std::multiset<int>{8, 12}));
}

TEST(FastPath, CopiesAndResetStartWithoutTrackedMarkers) {
  const Sequence sequence;
  const sim::Marker none = sim::FacingCamera(0, 0.15, {0.0, 0.0, -5.0});
  Detector detector;
  for (int k = 0; k < 2; ++k) Detect(sequence.Frame(k, none, 100), detector);
  EXPECT_EQ(detector.tracking_stats().tracked_frames, 1u);
  const Detector copy(detector);
  EXPECT_EQ(copy.tracking_stats().tracked_frames + copy.tracking_stats().full_searches, 0u);
  detector.ResetTracking();
  Detect(sequence.Frame(2, none, 100), detector);
  EXPECT_EQ(detector.tracking_stats().full_searches, 2u);  // the first frame and the one after the reset
}

// DetectorConfig::threads fixes how the frame is searched (its full-resolution strips) whatever OpenCV's
// thread count: the same pixels searched and the same markers and corners, to the bit, at one, two and
// three OpenCV threads; 0 follows OpenCV's count. More strips search more pixels (their overlaps).
TEST(FastPath, ThreadsSettingFixesTheSearchWhateverOpenCVsThreadCount) {
  const int saved = cv::getNumThreads();
  struct Run {
    std::vector<ArucoTag> tags;
    unsigned long long pixels;
  };
  const auto run = [](const Photo& photo, int opencv_threads, int threads) {
    cv::setNumThreads(opencv_threads);
    DetectorConfig config;
    config.dictionary = photo.dictionary;
    config.threads = threads;
    const Detector detector(config);
    const std::vector<ArucoTag> tags = Detect(test::LoadGrey(photo.file), detector);
    return Run{tags, detector.tracking_stats().searched_pixels};
  };
  const auto same = [](const Run& a, const Run& b) { return a.pixels == b.pixels && SameTags(a.tags, b.tags); };
  for (const Photo& photo : {kPhotos[1], kPhotos[4]}) {
    for (int threads = 1; threads <= 3; ++threads) {
      const Run one = run(photo, 1, threads);
      EXPECT_EQ(one.tags.size(), photo.markers) << photo.file << " threads " << threads;
      for (int opencv_threads = 2; opencv_threads <= 3; ++opencv_threads) {
        EXPECT_TRUE(same(one, run(photo, opencv_threads, threads)))
            << photo.file << " threads " << threads << " at " << opencv_threads << " OpenCV threads";
      }
      EXPECT_TRUE(same(run(photo, threads, 0), one)) << photo.file << " threads 0 at " << threads << " OpenCV threads";
    }
    EXPECT_LT(run(photo, 1, 1).pixels, run(photo, 1, 2).pixels) << photo.file;
    EXPECT_LT(run(photo, 1, 2).pixels, run(photo, 1, 3).pixels) << photo.file;
  }
  cv::setNumThreads(saved);
  DetectorConfig negative;
  negative.threads = -1;
  EXPECT_THROW(Detector{negative}, Error);
}

// The full-resolution level is searched in one strip per thread, and a marker too tall for the strips'
// overlap lies whole in none of them: those are searched again at full resolution around their
// coarser quads, and the quads are ordered by what they are, not by which strip listed them. So the
// markers, their corners and their order are the same to the bit whatever the thread count, with
// the default `threads` (OpenCV's count) too. Markers of 55-160 px across the cuts between two
// strips (row 360) and between three (rows 240 and 480). Without the second search 5 of the 9 views
// differ between one and two threads (a marker's corners, from a coarser quad); without the order, all
// 9 (the markers' order).
TEST(FastPath, TheSameMarkersWhateverTheThreadCount) {
  const int saved = cv::getNumThreads();
  const sim::Camera camera = test::RoverCamera();
  const double f = camera.K(1, 1), cy = camera.K(1, 2);
  const auto across = [&](int id, double x, double row, double range, double yaw, double roll) {
    return sim::FacingCamera(id, 0.15, {x, (row - cy) * range / f, range}, yaw, 10.0, roll);
  };
  int views = 0;
  for (const double range : {1.0, 1.6, 2.6}) {
    for (const double roll : {0.0, 25.0, 60.0}) {
      const std::vector<sim::Marker> markers = {across(3, -0.8 * range / 2.6, 360.0, range, 20.0, roll),
                                                across(11, -0.1, 240.0, range, -30.0, roll + 10.0),
                                                across(27, 0.7 * range / 2.6, 480.0, range, 0.0, roll + 40.0)};
      sim::RenderOptions options;
      options.seed = static_cast<unsigned>(++views);
      options.blur_sigma = 0.6;
      options.noise_sigma = 2.0;
      cv::Mat grey;
      PreprocessFrame(sim::RenderScene(camera, markers, options), grey);
      const std::string view = "range " + std::to_string(range) + " roll " + std::to_string(roll);
      cv::setNumThreads(1);
      DetectorConfig config;
      config.threads = 1;
      const std::vector<ArucoTag> one = Detect(grey, Detector(config));
      EXPECT_EQ(Ids(one), (std::multiset<int>{3, 11, 27})) << view;
      for (int threads = 2; threads <= 4; ++threads) {
        config.threads = threads;
        EXPECT_TRUE(SameTags(Detect(grey, Detector(config)), one)) << view << ", threads " << threads;
      }
      for (int opencv_threads = 1; opencv_threads <= 3; ++opencv_threads) {
        cv::setNumThreads(opencv_threads);
        EXPECT_TRUE(SameTags(Detect(grey, Detector()), one)) << view << ", threads 0 at " << opencv_threads
                                                         << " OpenCV threads";
      }
    }
  }
  cv::setNumThreads(saved);
  // A marker of 500 px across the seam: its neighbourhood would be over half the frame, so it keeps its
  // coarse quad at two threads (a bounded cost), and is still found, within hundredths of a pixel.
  sim::RenderOptions options;
  options.seed = 17;
  cv::Mat grey;
  PreprocessFrame(sim::RenderScene(camera, {across(5, 0.0, 360.0, 0.3, 15.0, 20.0)}, options), grey);
  DetectorConfig config;
  config.threads = 1;
  const std::vector<ArucoTag> one = Detect(grey, Detector(config));
  config.threads = 2;
  const std::vector<ArucoTag> two = Detect(grey, Detector(config));
  ASSERT_EQ(one.size(), 1u);
  ASSERT_EQ(two.size(), 1u);
  EXPECT_EQ(two[0].id, 5);
  for (int c = 0; c < 4; ++c) EXPECT_LT(cv::norm(two[0].corners[c] - one[0].corners[c]), 0.05) << "corner " << c;
}

TEST(FastPath, BadIntervalIsRejected) {
  DetectorConfig config;
  config.full_search_interval = 0;
  EXPECT_THROW(Detector{config}, Error);
}

}  // namespace
}  // namespace arucotag

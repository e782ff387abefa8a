// Every bad input gets an arucotag::Error that says what is wrong; nothing crashes.
#include <cmath>

#include <gtest/gtest.h>

#include <arucotag/arucotag.hpp>

namespace arucotag {
namespace {

template <typename F>
std::string ErrorOf(F&& f) {
  try {
    f();
  } catch (const Error& e) {
    return e.what();
  }
  return "";
}

TEST(BadInput, EmptyImageEverywhere) {
  cv::Mat empty, out;
  EXPECT_NE(ErrorOf([&] { PreprocessFrame(empty, out); }).find("empty"), std::string::npos);
  EXPECT_NE(ErrorOf([&] { Detect(empty, Detector()); }).find("empty"), std::string::npos);
  EXPECT_NE(ErrorOf([&] { DrawDetections(empty, {}); }).find("empty"), std::string::npos);
}

// Frames too small to hold a marker (a 1-pixel row, a thumbnail) give no tags on either path; the
// fast path's pyramid used to throw cv::Exception from cv::resize here.
TEST(BadInput, TinyFramesGiveNoTags) {
  for (const cv::Size size : {cv::Size(1, 1), cv::Size(3, 3), cv::Size(1, 50), cv::Size(50, 1), cv::Size(31, 200)}) {
    const cv::Mat frame(size, CV_8UC1, cv::Scalar(128));
    for (const bool fast : {true, false}) {
      DetectorConfig config;
      config.fast_path = fast;
      std::vector<ArucoTag> tags;
      EXPECT_NO_THROW(tags = Detect(frame, Detector(config))) << size << " fast " << fast;
      EXPECT_TRUE(tags.empty());
    }
  }
}

// Refinement from non-finite corners measures nothing and moves nothing.
TEST(BadInput, NonFiniteCornersToRefinement) {
  const cv::Mat grey(48, 64, CV_8UC1, cv::Scalar(128));
  std::array<cv::Point2f, 4> corners = {cv::Point2f(10, 10), cv::Point2f(30, 10), cv::Point2f(30, 30),
                                        cv::Point2f(std::nanf(""), 30)};
  EXPECT_EQ(RefineCornersOnEdges(grey, corners, 6), 0);
  EXPECT_EQ(corners[1], cv::Point2f(30, 10));
}

// Corners far outside the image (a bad track, a broken homography) measure nothing: no profile is
// read, nothing overflows the edge fit's fixed-point sample positions, and nothing moves.
TEST(BadInput, FarCornersToRefinement) {
  const cv::Mat grey(48, 64, CV_8UC1, cv::Scalar(128));
  for (const float far : {1e9f, -1e9f, 3e5f, 2e6f}) {
    std::array<cv::Point2f, 4> corners = {cv::Point2f(far, far), cv::Point2f(far + 20, far),
                                          cv::Point2f(far + 20, far + 20), cv::Point2f(far, far + 20)};
    const auto before = corners;
    EXPECT_EQ(RefineCornersOnEdges(grey, corners, 6), 0) << far;
    EXPECT_EQ(corners, before) << far;
  }
}

// A marker cut by the image's right and bottom edges: the profiles that would reach past the last
// pixel are skipped (the sanitizer build checks nothing is read there), the corners inside are still
// placed, and none moves far.
TEST(BadInput, MarkerCutByTheImageEdgeToRefinement) {
  cv::Mat grey(48, 64, CV_8UC1, cv::Scalar(230));
  // Black from (20, 10) to past the image's right and bottom edges.
  grey(cv::Rect(20, 10, 44, 38)).setTo(25);
  std::array<cv::Point2f, 4> corners = {cv::Point2f(20.4f, 10.3f), cv::Point2f(63.6f, 10.3f), cv::Point2f(63.6f, 47.6f),
                                        cv::Point2f(20.4f, 47.6f)};
  const auto before = corners;
  EXPECT_NO_THROW(RefineCornersOnEdges(grey, corners, 6));
  // The top-left corner's two edges lie inside: it goes to where the steps are, half-way between pixel
  // centres (19.5, 9.5).
  EXPECT_NEAR(corners[0].x, 19.5f, 0.05f);
  EXPECT_NEAR(corners[0].y, 9.5f, 0.05f);
  for (int i = 0; i < 4; ++i) EXPECT_LT(cv::norm(corners[i] - before[i]), 4.0) << i;
}

TEST(BadInput, FourChannelImageToDrawDetections) {
  cv::Mat bgra(48, 64, CV_8UC4, cv::Scalar::all(255));
  const std::string message = ErrorOf([&] { DrawDetections(bgra, {}); });
  EXPECT_NE(message.find("1 or 3 channels"), std::string::npos) << message;
  EXPECT_EQ(cv::countNonZero(bgra.reshape(1) != 255), 0) << "the image must be left untouched";
}

TEST(BadInput, SixteenBitImageToDetectSaysToPreprocess) {
  cv::Mat mono16(48, 64, CV_16UC1, cv::Scalar(1000));
  const std::string message = ErrorOf([&] { Detect(mono16, Detector()); });
  EXPECT_NE(message.find("PreprocessFrame"), std::string::npos) << message;
  // ... and PreprocessFrame does accept it.
  cv::Mat grey;
  PreprocessFrame(mono16, grey);
  EXPECT_EQ(grey.type(), CV_8UC1);
}

TEST(BadInput, SixteenBitColourAndFloatImagesRejected) {
  cv::Mat out;
  EXPECT_FALSE(ErrorOf([&] { PreprocessFrame(cv::Mat(4, 4, CV_16UC3), out); }).empty());
  EXPECT_FALSE(ErrorOf([&] { PreprocessFrame(cv::Mat(4, 4, CV_32FC1), out); }).empty());
  PreprocessOptions rgb;
  rgb.format = PixelFormat::kRgb8;
  EXPECT_NE(ErrorOf([&] { PreprocessFrame(cv::Mat(4, 4, CV_8UC1), out, rgb); }).find("does not match"),
            std::string::npos);
  EXPECT_NE(ErrorOf([] { PixelFormatFromEncoding("yuv422"); }).find("yuv422"), std::string::npos);
}

TEST(BadInput, ZeroIntrinsics) {
  ArucoTag tag;
  tag.corners = {{{10, 10}, {20, 10}, {20, 20}, {10, 20}}};
  const CameraModel zero = CameraModel::FromIntrinsics(cv::Matx33d::zeros(), {});
  const std::string message = ErrorOf([&] { EstimatePoseFromPNP(zero, tag); });
  EXPECT_NE(message.find("fx"), std::string::npos) << message;
  EXPECT_EQ(tag.pose_source, PoseSource::kNone);

  CameraModel nan_centre = CameraModel::FromIntrinsics(cv::Matx33d(500, 0, NAN, 0, 500, 240, 0, 0, 1), {});
  EXPECT_FALSE(ErrorOf([&] { EstimatePoseFromPNP(nan_centre, tag); }).empty());
  CameraModel odd_distortion = CameraModel::FromIntrinsics(cv::Matx33d(500, 0, 320, 0, 500, 240, 0, 0, 1), {0.1, 0.2, 0.3});
  EXPECT_NE(ErrorOf([&] { EstimatePoseFromPNP(odd_distortion, tag); }).find("3 coefficients"), std::string::npos);
}

TEST(BadInput, NonPositiveSideLength) {
  ArucoTag tag;
  tag.corners = {{{10, 10}, {20, 10}, {20, 20}, {10, 20}}};
  tag.side_length = 0.0;
  const CameraModel camera = CameraModel::FromIntrinsics(cv::Matx33d(500, 0, 320, 0, 500, 240, 0, 0, 1), {});
  EXPECT_NE(ErrorOf([&] { EstimatePoseFromPNP(camera, tag); }).find("side length"), std::string::npos);
}

TEST(BadInput, UnknownDictionaryListsValidNames) {
  DetectorConfig config;
  config.dictionary = "DICT_4X4_51";
  const std::string message = ErrorOf([&] { Detector detector(config); });
  EXPECT_NE(message.find("DICT_4X4_51"), std::string::npos);
  for (const auto& name : DictionaryNames()) EXPECT_NE(message.find(name), std::string::npos) << name;
  EXPECT_EQ(DictionaryNames().size(), 21u);
}

TEST(BadInput, BadDetectorParametersAreNamed) {
  DetectorConfig config;
  config.adaptive_thresh_win_size_min = 2;
  EXPECT_NE(ErrorOf([&] { Detector d(config); }).find("adaptive_thresh_win_size_min"), std::string::npos);
  config = {};
  config.side_lengths[7] = -0.1;
  EXPECT_NE(ErrorOf([&] { Detector d(config); }).find("id 7"), std::string::npos);
  EXPECT_NE(ErrorOf([] { CornerRefinementFromName("subpixel"); }).find("subpix"), std::string::npos);
}

TEST(BadInput, WrongSizeCloudIsAnError) {
  ArucoTag tag;
  tag.corners = {{{10, 10}, {20, 10}, {20, 20}, {10, 20}}};
  const cv::Mat cloud(240, 320, CV_32FC3, cv::Scalar::all(1.0));
  const std::string message = ErrorOf([&] { EstimatePoseFromPointCloud(cloud, {640, 480}, tag); });
  EXPECT_NE(message.find("320x240"), std::string::npos) << message;
  EXPECT_NE(message.find("640x480"), std::string::npos) << message;
  EXPECT_FALSE(ErrorOf([&] { EstimatePoseFromPointCloud(cv::Mat(480, 640, CV_32FC1), {640, 480}, tag); }).empty());
}

TEST(BadInput, AllNanCloudReportsFailureNotNan) {
  ArucoTag tag;
  tag.corners = {{{100, 100}, {200, 100}, {200, 200}, {100, 200}}};
  const float nan = std::numeric_limits<float>::quiet_NaN();
  const cv::Mat cloud(480, 640, CV_32FC3, cv::Scalar(nan, nan, nan));
  EXPECT_FALSE(EstimatePoseFromPointCloud(cloud, {640, 480}, tag));
  EXPECT_FALSE(tag.cloud.valid);
  EXPECT_EQ(tag.pose_source, PoseSource::kNone);
  EXPECT_FALSE(std::isfinite(tag.distance));
}

TEST(BadInput, TagPartlyOutsideTheCloudIsClipped) {
  ArucoTag tag;
  tag.corners = {{{-50, -50}, {60, -50}, {60, 60}, {-50, 60}}};
  const cv::Mat cloud(100, 100, CV_32FC3, cv::Scalar(0.0, 0.0, 2.0));
  ASSERT_TRUE(EstimatePoseFromPointCloud(cloud, {100, 100}, tag));
  EXPECT_NEAR(tag.cloud.centre[2], 2.0, 1e-6);
}

// Found by fuzz_pose (test/fuzz/corpus/pose/regress_cloud_min_points_0): with min_points 0 and
// no finite point the fallback took the median of nothing.
TEST(BadInput, NoCloudPointsIsNoPoseWhateverMinPoints) {
  ArucoTag tag;
  tag.corners = {{{10, 10}, {30, 10}, {30, 30}, {10, 30}}};
  const float nan = std::numeric_limits<float>::quiet_NaN();
  const cv::Mat cloud(48, 64, CV_32FC3, cv::Scalar(nan, nan, nan));
  CloudPoseOptions options;
  options.min_points = 0;
  options.min_plane_points = 0;
  EXPECT_FALSE(EstimatePoseFromPointCloud(cloud, cloud.size(), tag, options));
  EXPECT_FALSE(tag.cloud.valid);
  EXPECT_EQ(tag.pose_source, PoseSource::kNone);
}

// Found by fuzz_config (regress_threshold_windows_2575, regress_unwarped_side_32144): configs the
// validation let through that made one 160x120 frame take minutes or ask for 1 GB.
TEST(BadInput, DetectorConfigsThatWouldStallDetectionAreRefused) {
  DetectorConfig config;
  config.adaptive_thresh_win_size_min = 210;
  config.adaptive_thresh_win_size_max = 25959;
  EXPECT_NE(ErrorOf([&] { Detector d(config); }).find("adaptive_thresh_win_size_max"), std::string::npos);
  config.adaptive_thresh_win_size_max = 1001;
  config.adaptive_thresh_win_size_step = 1;
  EXPECT_NE(ErrorOf([&] { Detector d(config); }).find("threshold windows"), std::string::npos);
  config = {};
  config.marker_border_bits = 162;
  config.perspective_remove_pixel_per_cell = 98;
  EXPECT_NE(ErrorOf([&] { Detector d(config); }).find("perspective_remove_pixel_per_cell"), std::string::npos);
  // regress_timeout-*: 7x7 cells of 60 px (a 540 px square unwarped for every candidate) took 4-6 s a
  // frame under the sanitizers.
  config = {};
  config.dictionary = "DICT_7X7_1000";
  config.perspective_remove_pixel_per_cell = 60;
  EXPECT_NE(ErrorOf([&] { Detector d(config); }).find("perspective_remove_pixel_per_cell"), std::string::npos);
  // dynamic_reconfigure's extremes stay accepted: 197 windows up to 199 px, 20 px per cell of 7x7.
  config = {};
  config.dictionary = "DICT_7X7_1000";
  config.adaptive_thresh_win_size_min = 3;
  config.adaptive_thresh_win_size_max = 199;
  config.adaptive_thresh_win_size_step = 1;
  config.perspective_remove_pixel_per_cell = 20;
  EXPECT_EQ(ErrorOf([&] { Detector d(config); }), "");
}

// Found by fuzz_config (regress_clahe_tile_grid_huge, regress_unsharp_sigma_huge,
// regress_subpix_window_wider_than_frame, regress_approx_accuracy_out_of_range,
// regress_thresh_constant_huge): options OpenCV answered with a huge allocation or cv::Exception.
TEST(BadInput, OptionsOpenCvRefusesAreErrors) {
  const cv::Mat frame(40, 40, CV_8UC1, cv::Scalar(200));
  cv::Mat out;
  PreprocessOptions preprocess;
  preprocess.equalize = true;
  preprocess.clahe_tile_grid = 1 << 30;
  EXPECT_NE(ErrorOf([&] { PreprocessFrame(frame, out, preprocess); }).find("clahe_tile_grid"), std::string::npos);
  preprocess = {};
  preprocess.unsharp_amount = 1.0;
  preprocess.unsharp_sigma = 1e300;
  EXPECT_NE(ErrorOf([&] { PreprocessFrame(frame, out, preprocess); }).find("unsharp_sigma"), std::string::npos);
  DetectorConfig config;
  config.fast_path = false;
  config.corner_refinement = CornerRefinement::kSubpix;
  config.corner_refinement_win_size = 30;  // cv::cornerSubPix wants a frame of 2 * 30 + 5 px
  cv::Mat marker;
  cv::aruco::drawMarker(cv::aruco::getPredefinedDictionary(cv::aruco::DICT_4X4_50), 1, 30, marker);
  cv::Mat small(40, 40, CV_8UC1, cv::Scalar(255));
  marker.copyTo(small(cv::Rect(5, 5, 30, 30)));
  // Sub-pixel refinement is the core's, its window fitted to the marker's cells (5 px here): where
  // cv::aruco refused the frame, the marker is found and refined onto its corners.
  std::vector<ArucoTag> tags;
  EXPECT_EQ(ErrorOf([&] { tags = Detect(small, Detector(config)); }), "");
  ASSERT_EQ(tags.size(), 1u);
  EXPECT_NEAR(tags[0].corners[0].x, 4.5, 0.3);
  EXPECT_NEAR(tags[0].corners[0].y, 4.5, 0.3);
  config = {};
  config.adaptive_thresh_constant = -3.5e250;
  EXPECT_NE(ErrorOf([&] { Detector d(config); }).find("adaptive_thresh_constant"), std::string::npos);
}

// Found by fuzz_config (regress_max_perimeter_rate_1e300, regress_corner_window_1e9,
// regress_corner_window_slow): the fast path's int perimeter bounds
// overflowed; (regress_apriltag_inverted_null): OpenCV 4.6's detectMarkers dereferences null with
// apriltag refinement and inverted markers, so the combination never reaches it.
TEST(BadInput, DetectorConfigsOpenCvOrTheFastPathCannotRunAreRefused) {
  DetectorConfig config;
  config.max_marker_perimeter_rate = 1e300;
  EXPECT_NE(ErrorOf([&] { Detector d(config); }).find("max_marker_perimeter_rate"), std::string::npos);
  config.max_marker_perimeter_rate = 16.5;
  EXPECT_NE(ErrorOf([&] { Detector d(config); }).find("max_marker_perimeter_rate"), std::string::npos);
  config.min_marker_perimeter_rate = 1e300;  // bounded through max_marker_perimeter_rate
  EXPECT_NE(ErrorOf([&] { Detector d(config); }), "");
  config = {};
  config.corner_refinement = CornerRefinement::kApriltag;
  config.detect_inverted_marker = true;
  EXPECT_NE(ErrorOf([&] { Detector d(config); }).find("detect_inverted_marker"), std::string::npos);
  // The fast path's cornerSubPix window of
  // 1.6e9 px threw std::length_error on a worker thread; large windows and iterations took seconds.
  config = {};
  config.corner_refinement_win_size = 1643643908;
  EXPECT_NE(ErrorOf([&] { Detector d(config); }).find("corner_refinement_win_size"), std::string::npos);
  config = {};
  config.corner_refinement_max_iterations = 100000;
  EXPECT_NE(ErrorOf([&] { Detector d(config); }).find("corner_refinement_max_iterations"), std::string::npos);
  config.corner_refinement_win_size = 30;  // dynamic_reconfigure's largest
  config.corner_refinement_max_iterations = 200;
  EXPECT_EQ(ErrorOf([&] { Detector d(config); }), "");
  // dynamic_reconfigure's extremes stay accepted, and each of the two alone.
  for (const double max_rate : {0.1, 8.0}) {
    config = {};
    config.min_marker_perimeter_rate = 0.001;
    config.max_marker_perimeter_rate = max_rate;
    EXPECT_EQ(ErrorOf([&] { Detector d(config); }), "") << max_rate;
  }
  config.min_marker_perimeter_rate = 1.0;
  config.max_marker_perimeter_rate = 8.0;
  EXPECT_EQ(ErrorOf([&] { Detector d(config); }), "");
  config = {};
  config.corner_refinement = CornerRefinement::kApriltag;
  EXPECT_EQ(ErrorOf([&] { Detector d(config); }), "");
  config.corner_refinement = CornerRefinement::kEdge;
  config.detect_inverted_marker = true;
  EXPECT_EQ(ErrorOf([&] { Detector d(config); }), "");
}

// Found by fuzz_core (regress_draw_nan_corner): a NaN corner rounded to INT_MIN and overflowed.
TEST(BadInput, NonFiniteOrFarCornersToDrawDetections) {
  cv::Mat image(48, 64, CV_8UC3, cv::Scalar::all(128));
  for (const float bad : {std::numeric_limits<float>::quiet_NaN(), std::numeric_limits<float>::infinity(), 3e9f}) {
    ArucoTag tag;
    tag.id = 4;
    tag.corners = {{{10, 10}, {30, 10}, {30, 30}, {10, bad}}};
    EXPECT_NE(ErrorOf([&] { DrawDetections(image, {tag}); }).find("tag 4 has a corner"), std::string::npos) << bad;
    EXPECT_NE(ErrorOf([&] { LayoutLabels(image.size(), {tag}); }).find("tag 4 has a corner"), std::string::npos);
  }
}

}  // namespace
}  // namespace arucotag

// CameraModelFromInfo without a master: binned and cropped images described by a full-resolution
// camera_info give the full-resolution pose; fisheye infos work; bad infos are named.
#include <cmath>
#include <functional>
#include <string>
#include <vector>

#include <gtest/gtest.h>
#include <image_geometry/pinhole_camera_model.h>
#include <opencv2/calib3d.hpp>
#include <opencv2/imgproc.hpp>
#include <sensor_msgs/CameraInfo.h>

#include <arucotag/arucotag.hpp>
#include <arucotag/ros/conversions.hpp>
#include <arucotag/sim.hpp>

#include "rig.hpp"

namespace arucotag {
namespace {

constexpr double kDeg = M_PI / 180.0;
constexpr double kSide = 0.2;

/// 1280x720, 65 degrees across, plumb_bob distortion: the full sensor every test crops or bins.
sim::Camera FullCamera() {
  sim::Camera camera = sim::MakeCamera({1280, 720}, 65.0);
  camera.dist = {-0.12, 0.03, 0.0005, -0.0004, 0.0};
  return camera;
}

sim::Camera FisheyeCamera() { return sim::MakeFisheyeCamera({1280, 720}, 140.0, {0.04, -0.01, 0.002, -0.0003}); }

/// The full-resolution calibration of `camera` as its driver publishes it (the ROS tests' rig's).
sensor_msgs::CameraInfo InfoFor(const sim::Camera& camera) { return *test::Rig::InfoMessage(camera, ros::Time()); }

/// Sensor binning: every output pixel the mean of a b x b block (INTER_AREA is exactly that for an
/// integer factor).
cv::Mat Bin(const cv::Mat& image, int b) {
  cv::Mat binned;
  cv::resize(image, binned, cv::Size(image.cols / b, image.rows / b), 0, 0, cv::INTER_AREA);
  return binned;
}

// Through the camera model, as the nodelet detects: markers the lens bends keep the edge fit.
std::vector<ArucoTag> DetectIn(const cv::Mat& image, const CameraModel& camera) {
  DetectorConfig config;
  config.default_side_length = kSide;
  cv::Mat grey;
  PreprocessFrame(image, grey);
  return Detect(grey, Detector(config), camera);
}

double RotationError(const cv::Vec3d& a, const cv::Vec3d& b) {
  cv::Matx33d ra, rb;
  cv::Rodrigues(a, ra);
  cv::Rodrigues(b, rb);
  return std::acos(std::max(-1.0, std::min(1.0, (cv::trace(ra.t() * rb) - 1.0) / 2.0)));
}

/// Markers spread over the sensor: one near each corner of the frame and one in the middle.
std::vector<sim::Marker> Spread(const sim::Camera& camera, double range) {
  std::vector<sim::Marker> markers;
  const std::vector<cv::Point2d> at = {{0.5, 0.5}, {0.22, 0.25}, {0.8, 0.3}, {0.25, 0.75}, {0.78, 0.72}};
  for (size_t i = 0; i < at.size(); ++i) {
    // The ray through that image point, whichever the lens.
    cv::Mat px(1, 1, CV_64FC2, cv::Scalar(at[i].x * (camera.size.width - 1), at[i].y * (camera.size.height - 1)));
    cv::Mat xy;
    if (camera.fisheye) {
      cv::fisheye::undistortPoints(px, xy, camera.K, camera.dist);
    } else {
      cv::undistortPoints(px, xy, camera.K, camera.dist);
    }
    const cv::Vec2d n = xy.at<cv::Vec2d>(0);
    const cv::Vec3d ray = cv::normalize(cv::Vec3d(n[0], n[1], 1.0));
    markers.push_back(sim::FacingRay(static_cast<int>(i), kSide, ray * range, 25.0 + 3.0 * i, 40.0 * i, 15.0 * i));
  }
  return markers;
}

/// Detects in `image` (described by `info`) and checks every marker's pose against the truth:
/// translation within 0.5 % of its range, rotation within 1 degree, reprojection error (image
/// pixels) below max_rms. Returns how many it checked.
int ExpectFullResolutionPoses(const cv::Mat& image, const sensor_msgs::CameraInfo& info, bool rectified,
                              const std::vector<sim::Marker>& truth, const std::string& what,
                              double max_rms = 0.1) {
  const CameraModel camera = CameraModelFromInfo(info, rectified, image.size());
  int checked = 0;
  for (ArucoTag tag : DetectIn(image, camera)) {
    const sim::Marker& marker = truth.at(tag.id);
    EXPECT_TRUE(EstimatePoseFromPNP(camera, tag)) << what << " id " << tag.id;
    const double range = cv::norm(marker.tvec);
    EXPECT_LT(cv::norm(tag.tvec - marker.tvec), 0.005 * range) << what << " id " << tag.id;
    EXPECT_LT(RotationError(tag.rvec, marker.rvec), 1.0 * kDeg) << what << " id " << tag.id;
    EXPECT_LT(tag.reprojection_error, max_rms) << what << " id " << tag.id << ": image pixels";
    ++checked;
  }
  return checked;
}

TEST(CameraModelFromInfo, BinnedImageGivesFullResolutionPose) {
  const sim::Camera full = FullCamera();
  const auto markers = Spread(full, 2.0);
  const cv::Mat image = sim::RenderScene(full, markers, {});
  sensor_msgs::CameraInfo info = InfoFor(full);
  EXPECT_EQ(ExpectFullResolutionPoses(image, info, false, markers, "full"), 5);
  info.binning_x = info.binning_y = 2;
  const cv::Mat half = Bin(image, 2);
  ASSERT_EQ(half.size(), cv::Size(640, 360));
  EXPECT_EQ(ExpectFullResolutionPoses(half, info, false, markers, "binned 2x"), 5);
  info.binning_y = 1;  // binning along x only (a 2:1 anamorphic image)
  cv::Mat wide;
  cv::resize(image, wide, cv::Size(640, 720), 0, 0, cv::INTER_AREA);
  EXPECT_EQ(ExpectFullResolutionPoses(wide, info, false, markers, "binned 2x1"), 5);
}

TEST(CameraModelFromInfo, BinnedPixelCentresMapToTheSensor) {
  // Corners found in the binned image land on the true full-resolution corners: the centre of
  // image pixel u is sensor pixel (u + 0.5) * 2 - 0.5. image_geometry's toFullResolution (u * 2)
  // would put them half a sensor pixel up and left.
  const sim::Camera full = FullCamera();
  const auto markers = Spread(full, 1.5);
  sensor_msgs::CameraInfo info = InfoFor(full);
  info.binning_x = info.binning_y = 2;
  const cv::Mat half = Bin(sim::RenderScene(full, markers, {}), 2);
  const CameraModel camera = CameraModelFromInfo(info, false, half.size());
  image_geometry::PinholeCameraModel geometry;
  geometry.fromCameraInfo(info);
  cv::Point2d mean_error, geometry_mean_error;
  int corners = 0;
  for (const ArucoTag& tag : DetectIn(half, camera)) {
    const auto truth = sim::ProjectCorners(full, markers.at(tag.id));
    for (int i = 0; i < 4; ++i, ++corners) {
      mean_error += camera.pixels.ToSensor(tag.corners[i]) - cv::Point2d(truth[i]);
      geometry_mean_error += geometry.toFullResolution(cv::Point2d(tag.corners[i])) - cv::Point2d(truth[i]);
    }
  }
  ASSERT_EQ(corners, 20);
  mean_error /= corners;
  geometry_mean_error /= corners;
  EXPECT_LT(std::abs(mean_error.x), 0.1);
  EXPECT_LT(std::abs(mean_error.y), 0.1);
  EXPECT_NEAR(geometry_mean_error.x, -0.5, 0.1);
  EXPECT_NEAR(geometry_mean_error.y, -0.5, 0.1);
}

TEST(CameraModelFromInfo, CroppedImageGivesFullResolutionPose) {
  const sim::Camera full = FullCamera();
  const auto markers = Spread(full, 2.0);
  const cv::Mat image = sim::RenderScene(full, markers, {});
  sensor_msgs::CameraInfo info = InfoFor(full);
  // Top-left quarter and a bit: markers 1 (and the middle one) inside; off-centre, so a principal
  // point taken as the crop's centre would show.
  const cv::Rect roi(100, 60, 620, 400);
  info.roi.x_offset = roi.x;
  info.roi.y_offset = roi.y;
  info.roi.width = roi.width;
  info.roi.height = roi.height;
  EXPECT_GE(ExpectFullResolutionPoses(image(roi).clone(), info, false, markers, "roi"), 2);
  // Crop, then bin (the order REP 104 and image_geometry use).
  const cv::Rect wide_roi(320, 180, 960, 540);
  info.roi.x_offset = wide_roi.x;
  info.roi.y_offset = wide_roi.y;
  info.roi.width = wide_roi.width;
  info.roi.height = wide_roi.height;
  info.binning_x = info.binning_y = 2;
  EXPECT_GE(ExpectFullResolutionPoses(Bin(image(wide_roi), 2), info, false, markers, "roi + binned"), 2);
}

TEST(CameraModelFromInfo, RectifiedBinnedImageUsesProjection) {
  // A rectified image: no distortion, P its camera matrix; K and D describe the raw image and must
  // be ignored (deliberately different here).
  const sim::Camera rect = sim::MakeCamera({1280, 720}, 70.0);
  const auto markers = Spread(rect, 2.0);
  const cv::Mat image = sim::RenderScene(rect, markers, {});
  sensor_msgs::CameraInfo info = InfoFor(rect);
  info.K[0] *= 1.1;
  info.K[2] += 30.0;
  info.D = {-0.3, 0.1, 0.0, 0.0, 0.0};
  info.binning_x = info.binning_y = 2;
  EXPECT_EQ(ExpectFullResolutionPoses(Bin(image, 2), info, true, markers, "rectified binned"), 5);
  info.binning_x = info.binning_y = 1;
  const cv::Rect roi(640, 0, 640, 720);
  info.roi.x_offset = roi.x;
  info.roi.width = roi.width;
  info.roi.height = roi.height;
  EXPECT_GE(ExpectFullResolutionPoses(image(roi).clone(), info, true, markers, "rectified roi"), 2);
}

TEST(CameraModelFromInfo, FisheyeInfo) {
  const sim::Camera fisheye = FisheyeCamera();
  const auto markers = Spread(fisheye, 1.2);
  const cv::Mat image = sim::RenderScene(fisheye, markers, {});
  sensor_msgs::CameraInfo info = InfoFor(fisheye);
  ASSERT_EQ(info.distortion_model, "equidistant");
  EXPECT_EQ(ExpectFullResolutionPoses(image, info, false, markers, "fisheye"), 5);
  info.binning_x = info.binning_y = 2;
  // Binned, the off-axis markers are 40 px squares whose edges the lens bends. The whole-pattern
  // fit's straight-edged model put their corners up to 0.7 px towards the image centre (reprojection
  // RMS 0.12-0.24 px); through the lens model Detect leaves them to the edge fit, which follows the
  // bend (RMS at most 0.015 px).
  EXPECT_EQ(ExpectFullResolutionPoses(Bin(image, 2), info, false, markers, "fisheye binned"), 5);
}

TEST(CameraModelFromInfo, InfosAreCheckedAndProblemsNamed) {
  const sim::Camera full = FullCamera();
  const cv::Size size = full.size;
  struct Case {
    std::string what;
    std::function<void(sensor_msgs::CameraInfo&)> edit;
    bool rectified;
    cv::Size image_size;
    std::string error;  ///< a part of the message; empty: accepted
  };
  const auto set_roi = [](int x, int y, int w, int h) {
    return [=](sensor_msgs::CameraInfo& info) {
      info.roi.x_offset = x;
      info.roi.y_offset = y;
      info.roi.width = w;
      info.roi.height = h;
    };
  };
  const std::vector<Case> cases = {
      {"as calibrated", [](auto&) {}, false, size, ""},
      {"zero K", [](auto& info) { info.K.fill(0.0); }, false, size, "K is all zero"},
      {"NaN fy", [](auto& info) { info.K[4] = NAN; }, false, size, "K has a NaN or infinite"},
      {"negative fx", [](auto& info) { info.K[0] = -800.0; }, false, size, "fx"},
      {"infinite P, rectified", [](auto& info) { info.P[2] = INFINITY; }, true, size, "P has a NaN or infinite"},
      {"infinite P, raw (P unused)", [](auto& info) { info.P[2] = INFINITY; }, false, size, ""},
      {"zero P", [](auto& info) { info.P.fill(0.0); }, true, size, "P is all zero"},
      {"binned info, full image", [](auto& info) { info.binning_x = info.binning_y = 2; }, false, size,
       "is for a 640x360 image (1280x720 sensor, roi 0,0 1280x720, binning 2x2) but the image is 1280x720"},
      {"roi beyond the sensor", set_roi(1000, 0, 400, 300), false, {400, 300}, "roi does not lie within the sensor"},
      {"roi inside the sensor", set_roi(800, 0, 400, 300), false, {400, 300}, ""},
      {"roi, full image", set_roi(800, 0, 400, 300), false, size, "is for a 400x300 image"},
      {"roi offset without size", set_roi(8, 8, 0, 0), false, size, "roi does not lie within the sensor"},
      {"unknown model", [](auto& info) { info.distortion_model = "kannala_brandt"; }, false, size,
       "'kannala_brandt' is not supported"},
      {"unknown model, rectified (D unused)", [](auto& info) { info.distortion_model = "kannala_brandt"; }, true,
       size, ""},
      {"unknown model, zero D",
       [](auto& info) {
         info.distortion_model = "kannala_brandt";
         info.D.assign(5, 0.0);
       },
       false, size, ""},
      {"no model named, plumb_bob's D (older drivers)", [](auto& info) { info.distortion_model = ""; }, false, size,
       ""},
      {"equidistant with 5 coefficients", [](auto& info) { info.distortion_model = "equidistant"; }, false, size,
       "needs 4"},
      {"plumb_bob with 3 coefficients", [](auto& info) { info.D = {0.1, 0.2, 0.3}; }, false, size, "3 coefficients"},
      {"no size stated: nothing to compare", [](auto& info) { info.width = info.height = 0; }, false, {320, 240}, ""},
      // Found by fuzz_ros (test/fuzz/corpus/ros/regress_info_roi_2e31): past INT_MAX, image_geometry's
      // int views wrapped negative and the ROI's area overflowed; a binning of -1 divided INT_MIN.
      {"roi of 2^31 px, binning 2^32 - 1",
       [](auto& info) {
         info.roi.width = 1u << 31;
         info.roi.height = 300;
         info.binning_x = 0xffffffffu;
       },
       false, size, "above 32768 px"},
      {"sensor of 2^31 x 2^30 px", [](auto& info) { info.width = 1u << 31; info.height = 1u << 30; }, false, size,
       "2147483648x1073741824 sensor"},
  };
  for (const auto& c : cases) {
    sensor_msgs::CameraInfo info = InfoFor(full);
    c.edit(info);
    std::string message;
    try {
      CameraModelFromInfo(info, c.rectified, c.image_size);
    } catch (const Error& e) {
      message = e.what();
    }
    if (c.error.empty()) {
      EXPECT_EQ(message, "") << c.what;
    } else {
      EXPECT_NE(message.find(c.error), std::string::npos) << c.what << ": '" << message << "'";
    }
  }
}

TEST(CameraModelFromInfo, FromAKeptImageGeometryModel) {
  image_geometry::PinholeCameraModel geometry;
  std::string message;
  try {
    CameraModelFromInfo(geometry, false, {640, 360});
  } catch (const Error& e) {
    message = e.what();
  }
  EXPECT_EQ(message, "no camera_info received yet");
  sensor_msgs::CameraInfo info = InfoFor(FisheyeCamera());
  info.binning_x = info.binning_y = 2;
  geometry.fromCameraInfo(info);
  const CameraModel camera = CameraModelFromInfo(geometry, false, {640, 360});
  EXPECT_EQ(camera.distortion_model, DistortionModel::kEquidistant);
  EXPECT_EQ(camera.distortion, info.D);
  EXPECT_EQ(camera.K, FisheyeCamera().K);
  EXPECT_EQ(camera.pixels.scale, cv::Vec2d(2.0, 2.0));
  EXPECT_EQ(camera.pixels.offset, cv::Vec2d(0.5, 0.5));
}

}  // namespace
}  // namespace arucotag

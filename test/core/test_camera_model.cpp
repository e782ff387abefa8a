// The camera model's lens and pixel mapping: fisheye (equidistant) views rendered with a known pose,
// binned/cropped pixel grids, and the errors Validate names.
#include <functional>
#include <string>

#include <gtest/gtest.h>

#include "scene.hpp"

namespace arucotag {
namespace {

using test::kDeg;

// A 1280x720 fisheye seeing 140 degrees across, with a lens polynomial that is not the bare
// equidistant one (the coefficients bend theta_d by about 4 % at the image edge).
const std::vector<double> kFisheyeK = {0.04, -0.01, 0.002, -0.0003};
sim::Camera WideFisheye() { return sim::MakeFisheyeCamera({1280, 720}, 140.0, kFisheyeK); }

CameraModel ModelOf(const sim::Camera& camera) { return CameraModel::FromFisheye(camera.K, camera.dist); }

std::string ErrorOf(const std::function<void()>& f) {
  try {
    f();
  } catch (const Error& e) {
    return e.what();
  }
  return {};
}

// A marker `range` metres from the lens, `off_axis_deg` away from the optical axis towards image
// direction `azimuth_deg` (0 = right, 90 = down), viewed `tilt_deg` obliquely.
sim::Marker MarkerOffAxis(int id, double side, double range, double off_axis_deg, double azimuth_deg,
                          double tilt_deg) {
  const double a = off_axis_deg * kDeg, b = azimuth_deg * kDeg;
  const cv::Vec3d direction(std::sin(a) * std::cos(b), std::sin(a) * std::sin(b), std::cos(a));
  return sim::FacingRay(id, side, direction * range, tilt_deg, 30.0, 10.0);
}

ArucoTag TagAt(const std::array<cv::Point2f, 4>& corners, double side) {
  ArucoTag tag;
  tag.corners = corners;
  tag.side_length = side;
  return tag;
}

TEST(CameraModel, FisheyeExactCornersGiveExactPose) {
  const sim::Camera camera = WideFisheye();
  for (double off_axis : {0.0, 40.0, 65.0}) {
    const sim::Marker marker = MarkerOffAxis(0, 0.2, 2.0, off_axis, 200.0, 25.0);
    ArucoTag tag = TagAt(sim::ProjectCorners(camera, marker), marker.side);
    ASSERT_TRUE(EstimatePoseFromPNP(ModelOf(camera), tag)) << off_axis;
    EXPECT_LT(cv::norm(tag.tvec - marker.tvec), 1e-4) << off_axis;  // float corners: ~1e-5 px
    EXPECT_LT(test::RotationError(tag.rvec, marker.rvec), 0.01 * kDeg) << off_axis;
    EXPECT_LT(tag.reprojection_error, 1e-3) << off_axis;

    // Off axis, the same corners read through a pinhole model with the same numbers land far off
    // the truth, so the model really is the fisheye one.
    if (off_axis == 0.0) continue;
    ArucoTag pinhole = TagAt(sim::ProjectCorners(camera, marker), marker.side);
    ASSERT_TRUE(EstimatePoseFromPNP(CameraModel::FromIntrinsics(camera.K, camera.dist), pinhole));
    EXPECT_GT(cv::norm(pinhole.tvec - marker.tvec), 0.05 * 2.0) << off_axis;
  }
}

TEST(CameraModel, FisheyeRenderMatchesProjection) {
  // The renderer inverts the lens per pixel (cv::fisheye::undistortPoints); the truth projects it
  // forwards (cv::fisheye::projectPoints): detected corners agree when both are right.
  const sim::Camera camera = WideFisheye();
  const std::vector<sim::Marker> markers = {MarkerOffAxis(1, 0.25, 1.5, 0.0, 0.0, 20.0),
                                            MarkerOffAxis(2, 0.3, 1.2, 60.0, 0.0, 15.0),
                                            MarkerOffAxis(3, 0.3, 1.5, 50.0, 160.0, 30.0)};
  const auto tags = test::RenderAndDetect(camera, markers);
  ASSERT_EQ(tags.size(), markers.size());
  for (const auto& tag : tags) {
    const auto truth = sim::ProjectCorners(camera, markers[tag.id - 1]);
    for (int i = 0; i < 4; ++i) {
      EXPECT_LT(cv::norm(tag.corners[i] - truth[i]), 0.15) << "id " << tag.id << " corner " << i;
    }
  }
}

TEST(CameraModel, FisheyeRenderedViewGivesKnownPose) {
  const sim::Camera camera = WideFisheye();
  struct Case {
    double side, range, off_axis, azimuth, tilt;
  };
  // Centre, strong distortion towards the left/right edges, a corner of the image and 3 m away.
  const std::vector<Case> cases = {{0.2, 1.0, 0.0, 0.0, 25.0},   {0.3, 2.0, 55.0, 0.0, 30.0},
                                   {0.3, 1.5, 62.0, 180.0, 20.0}, {0.3, 2.0, 45.0, 210.0, 35.0},
                                   {0.4, 3.0, 30.0, 300.0, 30.0}, {0.3, 1.2, 30.0, 90.0, 40.0}};
  for (const auto& c : cases) {
    const sim::Marker marker = MarkerOffAxis(7, c.side, c.range, c.off_axis, c.azimuth, c.tilt);
    DetectorConfig config;
    config.default_side_length = c.side;
    const auto tags = test::RenderAndDetect(camera, {marker}, config);
    ASSERT_EQ(tags.size(), 1u) << c.range << " m, " << c.off_axis << " deg";
    ArucoTag tag = tags[0];
    ASSERT_TRUE(EstimatePoseFromPNP(ModelOf(camera), tag));
    const double range = cv::norm(marker.tvec);
    EXPECT_LT(cv::norm(tag.tvec - marker.tvec), 0.005 * range) << c.range << " m, " << c.off_axis << " deg";
    EXPECT_LT(test::RotationError(tag.rvec, marker.rvec), 1.0 * kDeg) << c.range << " m, " << c.off_axis << " deg";
    EXPECT_LT(tag.reprojection_error, 0.2) << c.range << " m, " << c.off_axis << " deg";
  }
}

TEST(CameraModel, PixelMappingOfBinningAndRoi) {
  const PixelMapping mapping = PixelMapping::FromBinningAndRoi(2, 4, {100, 40});
  // Image pixel (0, 0) is the middle of sensor pixels 100..101 x 40..43.
  EXPECT_DOUBLE_EQ(mapping.ToSensor({0, 0}).x, 100.5);
  EXPECT_DOUBLE_EQ(mapping.ToSensor({0, 0}).y, 41.5);
  EXPECT_DOUBLE_EQ(mapping.ToSensor({10, 3}).x, 120.5);
  EXPECT_DOUBLE_EQ(mapping.ToSensor({10, 3}).y, 53.5);
  const cv::Point2d back = mapping.ToImage(mapping.ToSensor({12.25, 7.75}));
  EXPECT_NEAR(back.x, 12.25, 1e-12);
  EXPECT_NEAR(back.y, 7.75, 1e-12);
  EXPECT_TRUE(PixelMapping().IsIdentity());
  EXPECT_TRUE(PixelMapping::FromBinningAndRoi(1, 1, {0, 0}).IsIdentity());
  EXPECT_FALSE(mapping.IsIdentity());
  EXPECT_NE(ErrorOf([] { PixelMapping::FromBinningAndRoi(0, 2, {0, 0}); }).find("binning"), std::string::npos);
}

TEST(CameraModel, BinnedCornersGiveTheFullResolutionPose) {
  // Corners in a 2x-binned, cropped image of a distorted pinhole and of a fisheye: the pose is the
  // full-resolution one and the error is measured in the small image's pixels.
  for (const bool fisheye : {false, true}) {
    const sim::Camera camera = fisheye ? WideFisheye() : test::RoverCamera(true);
    CameraModel model = fisheye ? ModelOf(camera) : test::ToModel(camera);
    model.pixels = PixelMapping::FromBinningAndRoi(2, 2, {64, 32});
    const sim::Marker marker = MarkerOffAxis(0, 0.2, 1.8, 20.0, 30.0, 30.0);
    std::array<cv::Point2f, 4> binned;
    const auto full = sim::ProjectCorners(camera, marker);
    for (int i = 0; i < 4; ++i) binned[i] = model.pixels.ToImage(full[i]);
    ArucoTag tag = TagAt(binned, marker.side);
    ASSERT_TRUE(EstimatePoseFromPNP(model, tag));
    EXPECT_LT(cv::norm(tag.tvec - marker.tvec), 1e-4) << fisheye;
    EXPECT_LT(tag.reprojection_error, 1e-3) << fisheye;
    const auto projected = model.Project({{0, 0, 0}}, marker.rvec, marker.tvec);
    const cv::Point2d centre = model.pixels.ToImage(sim::ProjectCentre(camera, marker));
    EXPECT_NEAR(projected[0].x, centre.x, 1e-3);
    EXPECT_NEAR(projected[0].y, centre.y, 1e-3);

    // One corner 1 image pixel off: the error is in image pixels, not the sensor's twice larger ones.
    tag = TagAt(binned, marker.side);
    tag.corners[0].x += 1.0f;
    ASSERT_TRUE(EstimatePoseFromPNP(model, tag));
    EXPECT_GT(tag.reprojection_error, 0.1) << fisheye;
    EXPECT_LT(tag.reprojection_error, 0.5) << fisheye;  // 1 px over 8 coordinates, partly absorbed
  }
}

TEST(CameraModel, ValidateNamesTheProblem) {
  const cv::Matx33d K(500, 0, 320, 0, 500, 240, 0, 0, 1);
  EXPECT_EQ(ErrorOf([&] { CameraModel::FromFisheye(K, {0.1, 0, 0, 0}).Validate(); }), "");
  EXPECT_NE(ErrorOf([&] { CameraModel::FromFisheye(K, {0.1, 0, 0, 0, 0}).Validate(); }).find("needs 4"),
            std::string::npos);
  EXPECT_NE(ErrorOf([&] { CameraModel::FromFisheye(K, {0.1, NAN, 0, 0}).Validate(); }).find("not finite"),
            std::string::npos);
  EXPECT_NE(ErrorOf([&] { CameraModel::FromIntrinsics(cv::Matx33d(500, 0, 320, 0, 500, 240, 0, 0, 0), {}).Validate(); })
                .find("0 0 1"),
            std::string::npos);
  EXPECT_NE(ErrorOf([&] { CameraModel::FromIntrinsics(cv::Matx33d(500, INFINITY, 320, 0, 500, 240, 0, 0, 1), {}).Validate(); })
                .find("skew"),
            std::string::npos);
  CameraModel bad_mapping = CameraModel::FromIntrinsics(K, {});
  bad_mapping.pixels.scale = cv::Vec2d(0.0, 1.0);
  EXPECT_NE(ErrorOf([&] { bad_mapping.Validate(); }).find("pixel mapping"), std::string::npos);
}

}  // namespace
}  // namespace arucotag

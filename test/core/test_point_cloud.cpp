// Pose from an organized cloud of a rendered scene with stereo-like holes and depth noise.
#include <gtest/gtest.h>

#include "scene.hpp"

namespace arucotag {
namespace {

using test::kDeg;

struct Scene {
  sim::Camera camera = test::RoverCamera();
  sim::Marker marker;
  ArucoTag tag;
  cv::Mat cloud;
};

Scene MakeScene(const sim::Marker& marker, double nan_fraction, double noise, unsigned seed = 2) {
  Scene s;
  s.marker = marker;
  cv::Mat depth;
  const cv::Mat image = sim::RenderScene(s.camera, {marker}, sim::RenderOptions(), &depth);
  sim::CloudOptions cloud_options;
  cloud_options.nan_fraction = nan_fraction;
  cloud_options.depth_noise_sigma = noise;
  cloud_options.seed = seed;
  s.cloud = sim::MakeOrganizedCloud(s.camera, depth, cloud_options);
  cv::Mat grey;
  PreprocessFrame(image, grey);
  auto tags = Detect(grey, Detector());
  EXPECT_EQ(tags.size(), 1u);
  if (!tags.empty()) s.tag = tags[0];
  return s;
}

TEST(PointCloud, HolesAndNoiseGiveDistanceWithin1PercentAndYawWithinHalfDegree) {
  int checked = 0;
  for (double range : {1.0, 2.5, 5.0, 8.0}) {
    for (double tilt : {0.0, 40.0}) {
      const sim::Marker marker = sim::FacingCamera(4, 0.15, {0.3 * range, 0.1 * range, range}, tilt, 0.0, 15.0);
      Scene s = MakeScene(marker, 0.30, 0.01, 3 + checked);
      ASSERT_TRUE(EstimatePoseFromPointCloud(s.cloud, s.camera.size, s.tag)) << range;
      const double range_true = cv::norm(marker.tvec);
      EXPECT_EQ(s.tag.pose_source, PoseSource::kPointCloud);
      EXPECT_NEAR(s.tag.distance, range_true, 0.01 * range_true) << "range " << range << " tilt " << tilt;
      EXPECT_NEAR(s.tag.yaw, std::atan2(marker.tvec[0], marker.tvec[2]), 0.5 * kDeg) << range << " " << tilt;
      EXPECT_GT(s.tag.cloud.points, 12);
      ++checked;
    }
  }
  EXPECT_EQ(checked, 8);
}

TEST(PointCloud, PlaneNormalAndOrientationAtCloseRange) {
  const sim::Marker marker = sim::FacingCamera(4, 0.15, {0.2, 0.0, 1.2}, 35.0, 10.0, 90.0);
  Scene s = MakeScene(marker, 0.30, 0.003);
  ASSERT_TRUE(EstimatePoseFromPointCloud(s.cloud, s.camera.size, s.tag));
  ASSERT_TRUE(s.tag.cloud.has_normal);
  ASSERT_TRUE(s.tag.cloud.has_rotation);
  cv::Matx33d truth;
  cv::Rodrigues(marker.rvec, truth);
  const cv::Vec3d normal_truth(truth(0, 2), truth(1, 2), truth(2, 2));
  EXPECT_GT(s.tag.cloud.normal.dot(normal_truth), std::cos(3.0 * kDeg));
  EXPECT_LE(test::RotationError(s.tag.rvec, marker.rvec), 3.0 * kDeg);
  EXPECT_LT(s.tag.cloud.plane_rms, 0.02);
}

TEST(PointCloud, FlyingPixelsDoNotMoveTheCentre) {
  const sim::Marker marker = sim::FacingCamera(4, 0.15, {0.0, 0.0, 2.0});
  Scene s = MakeScene(marker, 0.1, 0.002);
  // Every 7th pixel jumps to the background wall, like stereo mismatches at edges.
  for (int v = 0; v < s.cloud.rows; ++v) {
    for (int u = v % 7; u < s.cloud.cols; u += 7) {
      cv::Vec3f& p = s.cloud.at<cv::Vec3f>(v, u);
      if (std::isfinite(p[2])) p *= 10.0f;
    }
  }
  ASSERT_TRUE(EstimatePoseFromPointCloud(s.cloud, s.camera.size, s.tag));
  EXPECT_NEAR(s.tag.distance, 2.0, 0.02);
}

TEST(PointCloud, FewPointsGiveCentreWithoutNormalAndNeverNan) {
  const sim::Marker marker = sim::FacingCamera(4, 0.15, {0.0, 0.0, 2.0});
  Scene s = MakeScene(marker, 0.0, 0.0);
  // Keep only a handful of points inside the tag.
  const cv::Point2f centre = FindTagCenter(s.tag);
  cv::Mat sparse(s.cloud.size(), CV_32FC3, cv::Scalar::all(std::numeric_limits<float>::quiet_NaN()));
  for (int dv = -3; dv <= 3; dv += 3)
    for (int du = -6; du <= 6; du += 3) {
      const cv::Point p(cvRound(centre.x) + du, cvRound(centre.y) + dv);
      sparse.at<cv::Vec3f>(p) = s.cloud.at<cv::Vec3f>(p);
    }
  CloudPoseOptions options;
  options.min_points = 10;
  ASSERT_TRUE(EstimatePoseFromPointCloud(sparse, s.camera.size, s.tag, options));
  EXPECT_EQ(s.tag.cloud.points, 15);
  EXPECT_FALSE(s.tag.cloud.has_normal);
  EXPECT_NEAR(s.tag.distance, 2.0, 0.01);
  EXPECT_TRUE(std::isfinite(s.tag.rvec[0]) && std::isfinite(s.tag.rvec[1]) && std::isfinite(s.tag.rvec[2]));
  // Nothing measured the orientation: the guess faces the camera upright (marker x right, y up).
  EXPECT_LE(test::RotationError(s.tag.rvec, marker.rvec), 1.0 * kDeg);

  options.min_points = 16;
  ArucoTag fresh = s.tag;
  fresh.cloud = CloudResult();
  fresh.pnp = PnpResult();
  EXPECT_FALSE(EstimatePoseFromPointCloud(sparse, s.camera.size, fresh, options));
  EXPECT_EQ(fresh.pose_source, PoseSource::kNone);
}

TEST(PointCloud, FusedPicksTheIppeSolutionTheCloudAgreesWith) {
  const sim::Marker marker = sim::FacingCamera(4, 0.15, {0.1, 0.05, 2.0}, 30.0, 0.0, 0.0);
  Scene s = MakeScene(marker, 0.2, 0.005);
  const CameraModel camera = test::ToModel(s.camera);
  ASSERT_TRUE(EstimatePoseFromPNP(camera, s.tag));
  ASSERT_EQ(s.tag.pnp.solutions, 2);
  // Make the corners prefer the wrong solution: swap the two, as a noisy frame can.
  std::swap(s.tag.pnp.rvec[0], s.tag.pnp.rvec[1]);
  std::swap(s.tag.pnp.tvec[0], s.tag.pnp.tvec[1]);
  std::swap(s.tag.pnp.rms[0], s.tag.pnp.rms[1]);
  ResolvePose(s.tag, PoseSource::kPnp);
  EXPECT_GT(test::RotationError(s.tag.rvec, marker.rvec), 20.0 * kDeg) << "the swapped solution must be the flip";

  ASSERT_TRUE(EstimatePoseFromPointCloud(s.cloud, s.camera.size, s.tag));
  EXPECT_EQ(s.tag.pose_source, PoseSource::kFused);
  EXPECT_LE(test::RotationError(s.tag.rvec, marker.rvec), 1.0 * kDeg);
  EXPECT_LE(cv::norm(s.tag.tvec - marker.tvec), 0.01);
  EXPECT_LT(s.tag.depth_disagreement, 0.03);
  EXPECT_EQ(ResolvePose(s.tag, PoseSource::kPointCloud), PoseSource::kPointCloud);
  EXPECT_EQ(ResolvePose(s.tag, PoseSource::kNone), PoseSource::kNone);
  EXPECT_FALSE(s.tag.HasPose());
}

// Two IPPE-like solutions 2 x half_turn_deg apart (40 by default) and a cloud plane, to pin what
// FusedChoice weighs.
struct Choice {
  ArucoTag tag;
  cv::Vec3d normal[2];
  Choice(double e0, double e1, double half_turn_deg = 20.0) {
    tag.side_length = 0.15;
    tag.pnp.valid = true;
    tag.pnp.solutions = 2;
    // Facing the camera (marker z towards it), turned +-20 degrees about the vertical.
    for (int i = 0; i < 2; ++i) {
      const double a = (i == 0 ? half_turn_deg : -half_turn_deg) * CV_PI / 180.0;
      const cv::Matx33d turn(std::cos(a), 0, std::sin(a), 0, 1, 0, -std::sin(a), 0, std::cos(a));
      cv::Rodrigues(turn * cv::Matx33d(1, 0, 0, 0, -1, 0, 0, 0, -1), tag.pnp.rvec[i]);
    }
    tag.pnp.tvec = {cv::Vec3d(0.0, 0.0, 6.0), cv::Vec3d(0.0, 0.0, 6.0)};
    tag.pnp.rms = {e0, e1};
    for (int i = 0; i < 2; ++i) {
      cv::Matx33d r;
      cv::Rodrigues(tag.pnp.rvec[i], r);
      normal[i] = cv::Vec3d(r(0, 2), r(1, 2), r(2, 2));
    }
    tag.cloud.valid = tag.cloud.has_normal = true;
    tag.cloud.points = 200;
    tag.cloud.plane_rms = 0.002;
    tag.cloud.normal_sigma = 5.5 * CV_PI / 180.0;  // a clean plane: the systematic 5 degrees and a little
  }
};

TEST(PointCloud, FusedChoiceWeighsCornersAgainstTheCloud) {
  // Ambiguous corners (0.030 vs 0.032 px), a clean plane on solution 1: the cloud decides.
  Choice ambiguous(0.030, 0.032);
  ambiguous.tag.cloud.normal = ambiguous.normal[1];
  EXPECT_EQ(FusedChoice(ambiguous.tag), 1);

  // The same plane, but the corners are decisive (the other solution reprojects 0.5 px off, five
  // times the corner noise floor).
  Choice decisive(0.02, 0.5);
  decisive.tag.cloud.normal = decisive.normal[1];
  EXPECT_EQ(FusedChoice(decisive.tag), 0) << "a plane 40 degrees off must not overturn clear corners";

  // A plane perpendicular to both (the ground behind a stake, a misregistered cloud): no say.
  Choice ground(0.030, 0.032);
  ground.tag.cloud.normal = cv::normalize(ground.normal[0].cross(ground.normal[1]));
  EXPECT_EQ(FusedChoice(ground.tag), 0);

  // A very noisy plane (a stereo camera at 6 m: 30 degrees on the normal) near solution 1: not decisive.
  Choice noisy(0.030, 0.032);
  noisy.tag.cloud.normal = noisy.normal[1];
  noisy.tag.cloud.plane_rms = 0.06;
  noisy.tag.cloud.normal_sigma = 30.0 * CV_PI / 180.0;
  EXPECT_EQ(FusedChoice(noisy.tag), 0);

  // A far, steep marker (solutions 100 degrees apart, as at 9 m and 50 degrees off head-on) and a
  // stereo plane with 33 degrees of noise on its normal that lies 20 degrees from solution 1: within
  // its own noise of that solution, and far clearer evidence than the corners' (bench_pose seed 7,
  // frame 571, flipped when the plane had to lie within a fixed 15 degrees).
  Choice steep(0.089, 0.128, 50.0);
  // Turned from solution 1 further away from solution 0, in the plane of the two normals.
  const cv::Vec3d away = cv::normalize(steep.normal[0].dot(steep.normal[1]) * steep.normal[1] - steep.normal[0]);
  const double off = 20.0 * CV_PI / 180.0;
  steep.tag.cloud.normal = cv::normalize(std::cos(off) * steep.normal[1] + std::sin(off) * away);
  steep.tag.cloud.normal_sigma = 33.0 * CV_PI / 180.0;
  EXPECT_EQ(FusedChoice(steep.tag), 1);
  // The same plane 70 degrees from solution 1 is beyond twice its noise: another surface, no say.
  const double far_off = 70.0 * CV_PI / 180.0;
  steep.tag.cloud.normal = cv::normalize(std::cos(far_off) * steep.normal[1] + std::sin(far_off) * away);
  EXPECT_EQ(FusedChoice(steep.tag), 0);

  // Clear corners (0.001 against 0.078 px: ambiguity 0.008) and a stereo plane 9 degrees from the
  // other solution with 25 degrees of noise: the cloud's evidence outweighs the corners' by 11, but
  // the pick is clear and the plane noisy, and the pick stays (bench_pose seed 17, frame 303: the
  // plane was a correlated stereo patch and the override turned the pose 105 degrees). A precise
  // plane still overturns it (BundlePose.CloudResolvesTheFlipOfASingleFace).
  Choice clear(0.001, 0.078, 50.0);
  const double near_off = 9.0 * CV_PI / 180.0;
  clear.tag.cloud.normal = cv::normalize(std::cos(near_off) * clear.normal[1] + std::sin(near_off) * away);
  clear.tag.cloud.normal_sigma = 25.0 * CV_PI / 180.0;
  const FusedEvidence clear_evidence = WeighFusedEvidence(clear.tag);
  EXPECT_GT(clear_evidence.cloud - clear_evidence.corners, 9.0);
  EXPECT_EQ(FusedChoice(clear.tag), 0);
  clear.tag.cloud.normal_sigma = 8.0 * CV_PI / 180.0;
  EXPECT_EQ(FusedChoice(clear.tag), 1);

  // No plane, or one solution: the corners' pick.
  Choice flat(0.030, 0.032);
  flat.tag.cloud.normal = flat.normal[1];
  flat.tag.cloud.has_normal = false;
  EXPECT_EQ(FusedChoice(flat.tag), 0);
}

// The cloud's normal sigma follows the camera's depth noise at the tag's range, not only the
// plane residuals (correlated stereo noise tilts a small patch and leaves small residuals).
TEST(PointCloud, NormalSigmaFollowsTheDepthNoiseModel) {
  const sim::Marker marker = sim::FacingCamera(4, 0.15, {0.1, 0.05, 2.0}, 30.0, 0.0, 0.0);
  Scene near = MakeScene(marker, 0.0, 0.0);
  CloudPoseOptions quiet, zed;
  quiet.depth_noise_per_m2 = 0.0;
  ASSERT_TRUE(EstimatePoseFromPointCloud(near.cloud, near.camera.size, near.tag, quiet));
  const double clean = near.tag.cloud.normal_sigma;
  EXPECT_NEAR(clean, 5.0 * CV_PI / 180.0, 0.5 * CV_PI / 180.0) << "noise-free: the systematic part alone";
  ASSERT_TRUE(EstimatePoseFromPointCloud(near.cloud, near.camera.size, near.tag, zed));
  // 0.0018 * 2^2 = 7.2 mm over a 3.7 cm lever arm and 5 independent points: about 2.2 degrees more.
  EXPECT_GT(near.tag.cloud.normal_sigma, clean);
  EXPECT_LT(near.tag.cloud.normal_sigma, 7.0 * CV_PI / 180.0);
}

}  // namespace
}  // namespace arucotag

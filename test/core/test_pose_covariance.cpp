// Pose covariances against known truth (Monte Carlo corners and rendered frames), what `ambiguity`
// means, and the orientation flag of guessed orientations.
#include <cstdio>

#include <gtest/gtest.h>

#include "scene.hpp"

namespace arucotag {
namespace {

using test::kDeg;
using test::Nees;
using test::RotationResidual;

// Corners with known Gaussian noise, solved many times: with the reported covariance rescaled to the
// true noise (covariance / corner_sigma^2 * sigma^2), the mean NEES of translation and rotation is
// 3 when the Jacobian, its rotation convention and the pixel mapping are right. Pinhole with
// distortion, binned pinhole and fisheye.
TEST(PoseCovariance, JacobianPredictsMonteCarloScatter) {
  const double sigma = 0.3;
  struct Case {
    const char* name;
    CameraModel camera;
    sim::Camera render;
  };
  std::vector<Case> cases;
  {
    const sim::Camera render = test::RoverCamera(true);
    cases.push_back({"pinhole distorted", test::ToModel(render), render});
  }
  {
    sim::Camera render = test::RoverCamera();
    CameraModel camera = test::ToModel(render);
    camera.pixels = PixelMapping::FromBinningAndRoi(2, 2, {0.0, 0.0});
    cases.push_back({"binned 2x2", camera, render});
  }
  {
    const sim::Camera render = sim::MakeFisheyeCamera({1280, 720}, 150.0, {0.02, -0.01, 0.003, 0.0});
    cases.push_back({"fisheye", CameraModel::FromFisheye(render.K, render.dist), render});
  }
  for (const auto& c : cases) {
    const sim::Marker marker = sim::FacingCamera(3, 0.15, {0.2, -0.1, 1.5}, 35.0, 15.0, 20.0);
    const auto truth = sim::ProjectCorners(c.render, marker);
    cv::RNG rng(11);
    double nees_t = 0.0, nees_r = 0.0;
    const int draws = 400;
    for (int i = 0; i < draws; ++i) {
      ArucoTag tag;
      for (int k = 0; k < 4; ++k) {
        cv::Point2d p = truth[k];
        if (!c.camera.pixels.IsIdentity()) p = c.camera.pixels.ToImage(p);
        tag.corners[k] = cv::Point2f(p + cv::Point2d(rng.gaussian(sigma), rng.gaussian(sigma)));
      }
      ASSERT_TRUE(EstimatePoseFromPNP(c.camera, tag)) << c.name;
      ASSERT_TRUE(tag.orientation_measured);
      const double scale = sigma * sigma / (tag.pnp.corner_sigma * tag.pnp.corner_sigma);
      const PoseCovariance covariance = tag.covariance * scale;
      nees_t += Nees(covariance, 0, tag.tvec - marker.tvec);
      nees_r += Nees(covariance, 3, RotationResidual(tag.rvec, marker.rvec));
    }
    nees_t /= draws;
    nees_r /= draws;
    std::printf("%s: mean NEES with the true noise: translation %.2f, rotation %.2f (3 expected)\n", c.name, nees_t,
                nees_r);
    EXPECT_NEAR(nees_t, 3.0, 0.6) << c.name;
    EXPECT_NEAR(nees_r, 3.0, 0.6) << c.name;
  }
}

// A rendered, preprocessed view of `marker` with sensor noise and blur drawn from `rng` up to the
// given sigmas (grey levels, px).
cv::Mat NoisyView(const sim::Camera& camera, const sim::Marker& marker, int seed, cv::RNG& rng, double max_noise,
                  double max_blur) {
  sim::RenderOptions options;
  options.seed = seed;
  options.noise_sigma = rng.uniform(0.0, max_noise);
  options.blur_sigma = rng.uniform(0.0, max_blur);
  cv::Mat grey;
  PreprocessFrame(sim::RenderScene(camera, {marker}, options), grey);
  return grey;
}

// Rendered frames, 1-15 m, 0-70 degrees, blur and sensor noise, the whole pipeline (detector corners,
// PnP, the covariance with its estimated corner noise) with `config`: the mean NEES of translation
// and of rotation lies within [min_nees, 6] per range bin (3 is calibrated). Flips (rotation error
// over 10 degrees) are counted apart: the covariance spans the other planar solution only as far as
// the corners' likelihood of it; at most `max_flip_share` of the markers found in a bin.
void CheckPnpNeesPerRangeBin(DetectorConfig config, double min_nees, double max_flip_share) {
  const sim::Camera camera = test::RoverCamera();
  const CameraModel model = test::ToModel(camera);
  const double side = 0.2;
  config.default_side_length = side;
  const Detector detector(config);
  const double edges[] = {1.0, 3.0, 6.0, 10.0, 15.0};
  struct Bin {
    int frames = 0, found = 0, flipped = 0, used = 0;
    double nees_t = 0.0, nees_r = 0.0;
  };
  Bin bins[4];
  cv::RNG rng(7);
  const int frames = 300;
  for (int f = 0; f < frames; ++f) {
    const double range = rng.uniform(1.0, 15.0);
    const double tilt = rng.uniform(0.0, 70.0);
    const sim::Marker marker = sim::RandomMarker(rng, camera, 5, side, range, range, tilt);
    const cv::Mat grey = NoisyView(camera, marker, f + 1, rng, 4.0, 1.2);
    int b = 0;
    while (b < 3 && marker.tvec[2] >= edges[b + 1]) ++b;
    Bin& bin = bins[b];
    ++bin.frames;
    auto tags = Detect(grey, detector);
    if (tags.size() != 1 || tags[0].id != 5 || !EstimatePoseFromPNP(model, tags[0])) continue;
    ++bin.found;
    const ArucoTag& tag = tags[0];
    const cv::Vec3d e_r = RotationResidual(tag.rvec, marker.rvec);
    if (cv::norm(e_r) > 10.0 * kDeg) {
      ++bin.flipped;
      continue;
    }
    ++bin.used;
    bin.nees_t += Nees(tag.covariance, 0, tag.tvec - marker.tvec);
    bin.nees_r += Nees(tag.covariance, 3, e_r);
  }
  std::printf("| range m | frames | found | flipped | mean NEES translation | mean NEES rotation |\n");
  for (int b = 0; b < 4; ++b) {
    const Bin& bin = bins[b];
    ASSERT_GT(bin.used, 20) << "bin " << b;
    const double t = bin.nees_t / bin.used, r = bin.nees_r / bin.used;
    std::printf("| %.0f-%.0f | %d | %d | %d | %.2f | %.2f |\n", edges[b], edges[b + 1], bin.frames, bin.found,
                bin.flipped, t, r);
    EXPECT_GE(t, min_nees) << edges[b] << "-" << edges[b + 1] << " m";
    EXPECT_LE(t, 6.0) << edges[b] << "-" << edges[b + 1] << " m";
    EXPECT_GE(r, min_nees) << edges[b] << "-" << edges[b + 1] << " m";
    EXPECT_LE(r, 6.0) << edges[b] << "-" << edges[b + 1] << " m";
    EXPECT_LE(bin.flipped, static_cast<int>(max_flip_share * bin.found)) << "flips are rare";
  }
}

TEST(PoseCovariance, PnpNeesPerRangeBin) { CheckPnpNeesPerRangeBin(DetectorConfig(), 1.5, 0.1); }

// The same with the edge fit's corners alone (pattern_fit_max_side 0: what markers past
// pattern_fit_max_side or pattern_fit_max_markers get): their covariance assumes the edge fit's larger
// corner noise (ArucoTag::pattern_fitted false). With the pattern fit's noise assumed instead the far
// bin's markers (13-20 px) read a mean translation NEES of 50 under 15 px and 23 over. The edge fit's
// error on small markers is heavy-tailed (most far better than the prior, the blurred and oblique ones worse):
// calibrated on bench_pose's markers, the prior is conservative on these (mean NEES about 1 at 6-10 m,
// 20-33 px), which is allowed, an overconfident one is not. Flips are more common without the
// pattern fit (bench_pose: 25 of 264 PnP poses at 6-10 m, 79 of 259 at 10-15 m, against 0 and 20).
TEST(PoseCovariance, EdgeFitNeesPerRangeBin) {
  DetectorConfig config;
  config.pattern_fit_max_side = 0;
  CheckPnpNeesPerRangeBin(config, 0.5, 0.2);
}

// The sample recording's lesson (its 7 m stake's track was refused by the tracker's gate): frames
// sent as JPEG (quality 80, image_transport's compressed default) move a far marker's corners by a few
// hundredths of a pixel more than the lossless renders' calibration assumes, and the four corners'
// 2-dof residual does not show it. With the camera's corner noise (CameraModel::corner_noise, its
// default) the mean NEES stays under the range bins' upper bound; without it the rotation's is above.
// The default is on the safe side here (measured 0.30 / 0.47): JPEG alone moves these still markers
// less than the recording's moving camera does with motion blur, noise and JPEG (0.03-0.07 px).
TEST(PoseCovariance, JpegFramesNeedTheCameraNoise) {
  const sim::Camera camera = test::RoverCamera();
  const CameraModel lossless = test::ToModel(camera);
  CameraModel jpeg = lossless;
  jpeg.corner_noise = CameraModel::kDefaultCornerNoise;
  const double side = 0.2;
  DetectorConfig config;
  config.default_side_length = side;
  const Detector detector(config);
  cv::RNG rng(11);
  int used = 0, flipped = 0;
  double nees_t[2] = {0.0, 0.0}, nees_r[2] = {0.0, 0.0};
  for (int f = 0; f < 120; ++f) {
    const double range = rng.uniform(5.0, 10.0);
    const sim::Marker marker = sim::RandomMarker(rng, camera, 5, side, range, range, rng.uniform(0.0, 40.0));
    sim::RenderOptions options;
    options.seed = f + 1;
    options.noise_sigma = rng.uniform(0.0, 2.0);
    options.blur_sigma = rng.uniform(0.0, 0.8);
    std::vector<uchar> bytes;
    ASSERT_TRUE(
        cv::imencode(".jpg", sim::RenderScene(camera, {marker}, options), bytes, {cv::IMWRITE_JPEG_QUALITY, 80}));
    cv::Mat grey;
    PreprocessFrame(cv::imdecode(bytes, cv::IMREAD_UNCHANGED), grey);
    auto tags = Detect(grey, detector);
    if (tags.size() != 1 || tags[0].id != 5) continue;
    ArucoTag with = tags[0], without = tags[0];
    ASSERT_TRUE(EstimatePoseFromPNP(jpeg, with));
    ASSERT_TRUE(EstimatePoseFromPNP(lossless, without));
    const ArucoTag* both[2] = {&with, &without};
    if (cv::norm(RotationResidual(with.rvec, marker.rvec)) > 10.0 * kDeg ||
        cv::norm(RotationResidual(without.rvec, marker.rvec)) > 10.0 * kDeg) {
      ++flipped;
      continue;
    }
    ++used;
    for (int i = 0; i < 2; ++i) {
      nees_t[i] += Nees(both[i]->covariance, 0, both[i]->tvec - marker.tvec);
      nees_r[i] += Nees(both[i]->covariance, 3, RotationResidual(both[i]->rvec, marker.rvec));
    }
  }
  ASSERT_GT(used, 80);
  for (int i = 0; i < 2; ++i) {
    nees_t[i] /= used;
    nees_r[i] /= used;
  }
  std::printf("JPEG q80, 0.2 m at 5-10 m, %d markers (%d flipped): mean NEES translation / rotation %.2f / %.2f "
              "with corner_noise %.2f px, %.2f / %.2f without\n",
              used, flipped, nees_t[0], nees_r[0], CameraModel::kDefaultCornerNoise, nees_t[1], nees_r[1]);
  EXPECT_GE(nees_t[0], 0.15) << "no wider than about 2.5 times the error";
  EXPECT_LE(nees_t[0], 6.0);
  EXPECT_GE(nees_r[0], 0.15) << "no wider than about 2.5 times the error";
  EXPECT_LE(nees_r[0], 6.0);
  EXPECT_GT(nees_r[1], 6.0) << "the lossless calibration alone is not overconfident on JPEG frames";
}

ArucoTag NoisyCorners(const sim::Camera& camera, const sim::Marker& marker, double sigma, int seed) {
  ArucoTag tag;
  tag.corners = sim::ProjectCorners(camera, marker);
  cv::RNG rng(seed);
  for (auto& c : tag.corners) c += cv::Point2f(rng.gaussian(sigma), rng.gaussian(sigma));
  return tag;
}

// Small near-frontal markers, rendered and detected: the two planar solutions lie a few degrees
// apart and the corners often pick the wrong one. The reported covariance holds both (the rival
// weighed by its likelihood), so the truth stays inside it; the covariance of the pick's
// neighbourhood alone put wrong picks at a rotation NEES in the hundreds.
TEST(PoseCovariance, AmbiguousPickCoversItsRival) {
  const sim::Camera camera = test::RoverCamera();
  const CameraModel model = test::ToModel(camera);
  DetectorConfig config;
  config.default_side_length = 0.2;
  const Detector detector(config);
  cv::RNG rng(5);
  int found = 0, wrong = 0, outside = 0, outside_alone = 0, outside_fused = 0;
  for (int f = 0; f < 80; ++f) {
    const double range = rng.uniform(8.0, 13.0);
    const sim::Marker marker = sim::RandomMarker(rng, camera, 5, 0.2, range, range, rng.uniform(0.0, 15.0));
    const cv::Mat grey = NoisyView(camera, marker, f + 1, rng, 3.0, 1.0);
    auto tags = Detect(grey, detector);
    if (tags.size() != 1 || tags[0].id != 5 || !EstimatePoseFromPNP(model, tags[0])) continue;
    const ArucoTag& tag = tags[0];
    ++found;
    if (tag.pnp.solutions == 2 && test::RotationError(tag.pnp.rvec[0], marker.rvec) >
                                      test::RotationError(tag.pnp.rvec[1], marker.rvec)) {
      ++wrong;
    }
    const cv::Vec3d e_r = RotationResidual(tag.rvec, marker.rvec);
    outside += Nees(tag.covariance, 3, e_r) > 16.27;  // chi-square 3 dof, 99.9 %
    outside_alone += Nees(tag.pnp.covariance[0], 3, e_r) > 16.27;
    // A cloud too sparse for a plane (its centre only) says nothing about the flip either.
    ArucoTag fused = tag;
    fused.cloud.valid = true;
    fused.cloud.points = 20;
    fused.cloud.centre = marker.tvec;
    fused.cloud.covariance = PoseCovariance::eye() * 1e-4;
    ASSERT_EQ(ResolvePose(fused, PoseSource::kFused), PoseSource::kFused);
    outside_fused += Nees(fused.covariance, 3, RotationResidual(fused.rvec, marker.rvec)) > 16.27;
  }
  std::printf("%d found, %d picks wrong; truth outside the 99.9 %% ellipsoid: %d with the rival (%d fused with a "
              "centre), %d without\n",
              found, wrong, outside, outside_fused, outside_alone);
  ASSERT_GE(found, 70);
  EXPECT_GT(wrong, found / 10) << "the scenes must be ambiguous to test anything";
  EXPECT_LE(outside, found / 20);
  EXPECT_LE(outside_fused, found / 20);
  EXPECT_GT(outside_alone, 2 * outside);
}

// ambiguity = best RMS / second RMS of the two planar solutions. A small frontal marker cannot tell
// its tilt's sign (high); a close marker turned 30 degrees can (low). Close markers with 1.5 px of
// corner noise made the old fallback (an absolute 1 px threshold) pair SQPNP's answer with IPPE's
// own near-copy of it: the pair must stay two distinct solutions, the best on the truth.
TEST(PoseCovariance, AmbiguityIsTheRatioOfThePlanarPair) {
  const sim::Camera camera = test::RoverCamera();
  const CameraModel model = test::ToModel(camera);
  for (int seed = 0; seed < 5; ++seed) {
    ArucoTag frontal = NoisyCorners(camera, sim::FacingCamera(3, 0.15, {0.3, 0.1, 8.0}), 0.3, seed);
    ASSERT_TRUE(EstimatePoseFromPNP(model, frontal));
    ASSERT_EQ(frontal.pnp.solutions, 2);
    EXPECT_NEAR(frontal.pnp.ambiguity, frontal.pnp.rms[0] / frontal.pnp.rms[1], 1e-12);
    EXPECT_GT(frontal.pnp.ambiguity, 0.5) << "seed " << seed;
  }
  for (int seed = 0; seed < 10; ++seed) {
    for (double tilt : {0.0, 30.0}) {
      const sim::Marker marker = sim::FacingCamera(3, 0.15, {0.05, 0.02, 0.5}, tilt, 0.0, 0.0);
      ArucoTag tag = NoisyCorners(camera, marker, 1.5, seed);
      ASSERT_TRUE(EstimatePoseFromPNP(model, tag));
      ASSERT_EQ(tag.pnp.solutions, 2);
      const double apart = test::RotationError(tag.pnp.rvec[0], tag.pnp.rvec[1]) / kDeg;
      EXPECT_GT(apart, 3.0) << "tilt " << tilt << " seed " << seed << ": the pair collapsed";
      EXPECT_LE(tag.pnp.rms[0], tag.pnp.rms[1]);
      EXPECT_LE(test::RotationError(tag.rvec, marker.rvec), 5.0 * kDeg) << "tilt " << tilt << " seed " << seed;
      if (tilt == 30.0) {
        EXPECT_LT(tag.pnp.ambiguity, 0.2) << "seed " << seed;
        EXPECT_GT(apart, 40.0) << "the second solution is the mirror pose";
      }
    }
  }
}

// A rival planar solution whose own covariance is unknown (a singular Jacobian) still widens the
// pick's by its distance, and never turns a measured pose's covariance into NaN.
TEST(PoseCovariance, RivalWithUnknownCovarianceStillCounts) {
  const sim::Camera camera = test::RoverCamera();
  ArucoTag tag = NoisyCorners(camera, sim::FacingCamera(3, 0.15, {0.3, 0.1, 8.0}, 5.0, 0.0, 0.0), 0.05, 3);
  ASSERT_TRUE(EstimatePoseFromPNP(test::ToModel(camera), tag));
  ASSERT_EQ(tag.pnp.solutions, 2);
  const PoseCovariance with_rival = tag.covariance;
  tag.pnp.covariance[1] = UnknownCovariance();
  ASSERT_EQ(ResolvePose(tag, PoseSource::kPnp), PoseSource::kPnp);
  for (int i = 0; i < 36; ++i) EXPECT_TRUE(std::isfinite(tag.covariance.val[i])) << i;
  double wider = 0.0;
  for (int i = 3; i < 6; ++i) {
    EXPECT_GE(tag.covariance(i, i), tag.pnp.covariance[0](i, i)) << i;
    wider += tag.covariance(i, i) - tag.pnp.covariance[0](i, i);
  }
  EXPECT_GT(wider, 0.0) << "an ambiguous pick's rival counts";
  for (int i = 3; i < 6; ++i) EXPECT_NEAR(tag.covariance(i, i), with_rival(i, i), 0.5 * with_rival(i, i)) << i;
}

// OpenCV's IPPE puts both solutions about 180 degrees off for an exactly frontal marker at the
// image centre; the refinement finds the truth without making the pair one solution twice.
TEST(PoseCovariance, DegenerateIppeKeepsTwoSolutions) {
  const sim::Camera camera = test::RoverCamera();
  const sim::Marker marker = sim::FacingCamera(3, 0.15, {0.0, 0.0, 2.0});
  ArucoTag tag;
  tag.corners = sim::ProjectCorners(camera, marker);
  ASSERT_TRUE(EstimatePoseFromPNP(test::ToModel(camera), tag));
  ASSERT_EQ(tag.pnp.solutions, 2);
  EXPECT_LE(test::RotationError(tag.rvec, marker.rvec), 0.1 * kDeg);
  EXPECT_GT(test::RotationError(tag.pnp.rvec[0], tag.pnp.rvec[1]), 1.0 * kDeg);
  EXPECT_LT(tag.pnp.ambiguity, 0.1);
  for (int i = 0; i < 36; ++i) EXPECT_TRUE(std::isfinite(tag.covariance.val[i]));
}

// A cloud too sparse for a plane leaves the orientation unmeasured: flagged, with pi^2 rotation
// variances and a finite centre covariance. A plane, or PnP, measures it.
TEST(PoseCovariance, GuessedOrientationIsFlagged) {
  const sim::Camera camera = test::RoverCamera();
  const sim::Marker marker = sim::FacingCamera(4, 0.15, {0.0, 0.0, 2.0}, 25.0, 0.0, 0.0);
  cv::Mat depth;
  sim::RenderScene(camera, {marker}, sim::RenderOptions(), &depth);
  sim::CloudOptions cloud_options;
  cloud_options.depth_noise_sigma = 0.005;
  const cv::Mat cloud = sim::MakeOrganizedCloud(camera, depth, cloud_options);
  ArucoTag tag;
  tag.corners = sim::ProjectCorners(camera, marker);

  ArucoTag none = tag;
  EXPECT_FALSE(none.orientation_measured);
  EXPECT_TRUE(std::isnan(none.covariance(0, 0)));

  ArucoTag dense = tag;
  ASSERT_TRUE(EstimatePoseFromPointCloud(cloud, camera.size, dense));
  ASSERT_TRUE(dense.cloud.has_rotation);
  EXPECT_TRUE(dense.orientation_measured);
  for (int i = 0; i < 6; ++i) {
    EXPECT_GT(dense.covariance(i, i), 0.0);
    EXPECT_LT(dense.covariance(i, i), std::pow(i < 3 ? 0.01 : 5.0 * kDeg, 2)) << i;
  }

  const cv::Point2f centre = FindTagCenter(tag);
  cv::Mat sparse(cloud.size(), CV_32FC3, cv::Scalar::all(std::numeric_limits<float>::quiet_NaN()));
  for (int dv = -3; dv <= 3; dv += 3) {
    for (int du = -6; du <= 6; du += 3) {
      const cv::Point p(cvRound(centre.x) + du, cvRound(centre.y) + dv);
      sparse.at<cv::Vec3f>(p) = cloud.at<cv::Vec3f>(p);
    }
  }
  CloudPoseOptions options;
  options.min_points = 10;
  ArucoTag guessed = tag;
  ASSERT_TRUE(EstimatePoseFromPointCloud(sparse, camera.size, guessed, options));
  ASSERT_FALSE(guessed.cloud.has_rotation);
  EXPECT_EQ(guessed.pose_source, PoseSource::kPointCloud);
  EXPECT_FALSE(guessed.orientation_measured);
  for (int i = 0; i < 3; ++i) {
    EXPECT_GT(guessed.covariance(i, i), 0.0);
    EXPECT_LT(guessed.covariance(i, i), 0.05 * 0.05);
    EXPECT_DOUBLE_EQ(guessed.covariance(3 + i, 3 + i), CV_PI * CV_PI);
  }
  EXPECT_GT(test::RotationError(guessed.rvec, marker.rvec), 20.0 * kDeg) << "the guess faces the camera";

  // PnP measures what the sparse cloud could not: the cloud's centre with PnP's rotation.
  ASSERT_TRUE(EstimatePoseFromPNP(test::ToModel(camera), guessed));
  EXPECT_EQ(ResolvePose(guessed, PoseSource::kPointCloud), PoseSource::kPointCloud);
  EXPECT_TRUE(guessed.orientation_measured);
  EXPECT_LT(guessed.covariance(3, 3), std::pow(5.0 * kDeg, 2));
  EXPECT_DOUBLE_EQ(guessed.covariance(0, 0), guessed.cloud.covariance(0, 0));
  EXPECT_DOUBLE_EQ(guessed.covariance(0, 3), 0.0);
  // Fused: the cloud picked a PnP solution and its centre updated it, so the pose is no less
  // certain than that solution alone.
  EXPECT_EQ(ResolvePose(guessed, PoseSource::kFused), PoseSource::kFused);
  EXPECT_TRUE(guessed.orientation_measured);
  const int best = FusedChoice(guessed);
  for (int i = 0; i < 6; ++i) EXPECT_LE(guessed.covariance(i, i), guessed.pnp.covariance[best](i, i) * (1.0 + 1e-9));
}

// The fused pose is PnP's chosen solution updated by the cloud's centre, each weighed by its
// covariance; a centre beyond the gate (another surface, a stale cloud) leaves PnP's pose alone.
TEST(PoseCovariance, FusedWeighsTheCloudCentreByBothCovariances) {
  ArucoTag tag;
  tag.pnp.valid = true;
  tag.pnp.solutions = 1;
  tag.pnp.rvec[0] = cv::Vec3d(CV_PI, 0.0, 0.0);
  tag.pnp.tvec[0] = cv::Vec3d(0.0, 0.0, 5.0);
  tag.pnp.rms[0] = 0.1;
  PoseCovariance pnp = PoseCovariance::zeros();
  for (int i = 0; i < 6; ++i) pnp(i, i) = 1e-4;
  pnp(2, 2) = 0.04;           // PnP's range is its weak direction: 0.2 m
  pnp(2, 4) = pnp(4, 2) = 1e-3;  // and it is correlated with a rotation about y
  tag.pnp.covariance[0] = pnp;
  tag.cloud.valid = true;
  tag.cloud.points = 500;
  tag.cloud.covariance = PoseCovariance::zeros();
  for (int i = 0; i < 3; ++i) tag.cloud.covariance(i, i) = 1e-4;
  tag.cloud.covariance(2, 2) = 0.04;
  for (int i = 3; i < 6; ++i) tag.cloud.covariance(i, i) = CV_PI * CV_PI;

  tag.cloud.centre = cv::Vec3d(0.0, 0.0, 5.3);
  ASSERT_EQ(ResolvePose(tag, PoseSource::kFused), PoseSource::kFused);
  EXPECT_NEAR(tag.tvec[2], 5.15, 1e-9) << "equal weights: half way";
  EXPECT_NEAR(tag.covariance(2, 2), 0.02, 1e-9);
  EXPECT_NEAR(tag.tvec[0], 0.0, 1e-12);
  // The correlation carries the range correction into the rotation: 1e-3 / 0.08 * 0.3 rad about y.
  EXPECT_NEAR(test::RotationError(tag.rvec, tag.pnp.rvec[0]), 1e-3 / 0.08 * 0.3, 1e-6);
  EXPECT_LT(tag.covariance(4, 4), pnp(4, 4));

  tag.cloud.centre = cv::Vec3d(0.0, 0.0, 7.0);  // 2 m off: 7 sigma
  ASSERT_EQ(ResolvePose(tag, PoseSource::kFused), PoseSource::kFused);
  EXPECT_EQ(tag.tvec, tag.pnp.tvec[0]);
  EXPECT_EQ(tag.covariance, pnp);
  EXPECT_NEAR(tag.depth_disagreement, 2.0, 1e-12);
}

// The cloud's covariance against clouds with a ZED 2's stereo noise (correlated in patches, holes,
// fattened edges), at 1.5-8 m and 0-50 degrees, the camera's noise model declared: the mean NEES of
// the centre and of the rotation lies within [0.5, 2] x 3. Correlated noise moves the whole patch,
// which the plane's residuals alone do not show (their covariance gave a mean NEES in the thousands).
TEST(PoseCovariance, CloudNeesUnderStereoNoise) {
  const sim::Camera camera = test::RoverCamera();
  const sim::DepthNoise zed = sim::DepthNoise::Zed2();
  CloudPoseOptions options;
  options.depth_noise_per_m2 = zed.disparity_sigma / (camera.K(0, 0) * zed.baseline);
  double nees_t = 0.0, nees_r = 0.0;
  int draws = 0;
  cv::RNG rng(5);
  for (const double range : {1.5, 3.0, 5.0, 8.0}) {
    for (int k = 0; k < 10; ++k) {
      const cv::Vec3d position(rng.uniform(-0.3, 0.3) * range, rng.uniform(-0.15, 0.15) * range, range);
      const sim::Marker marker = sim::FacingCamera(4, 0.15, position, rng.uniform(-50.0, 50.0),
                                                   rng.uniform(-20.0, 20.0), rng.uniform(-90.0, 90.0));
      cv::Mat depth;
      sim::RenderScene(camera, {marker}, sim::RenderOptions(), &depth);
      sim::CloudOptions cloud_options;
      cloud_options.stereo = zed;
      cloud_options.seed = 100 + draws;
      ArucoTag tag;
      tag.corners = sim::ProjectCorners(camera, marker);
      if (!EstimatePoseFromPointCloud(sim::MakeOrganizedCloud(camera, depth, cloud_options), camera.size, tag, options) ||
          !tag.cloud.has_rotation) {
        continue;
      }
      nees_t += Nees(tag.cloud.covariance, 0, tag.cloud.centre - marker.tvec);
      cv::Vec3d cloud_rvec;
      cv::Rodrigues(tag.cloud.rotation, cloud_rvec);
      nees_r += Nees(tag.cloud.covariance, 3, RotationResidual(cloud_rvec, marker.rvec));
      ++draws;
    }
  }
  ASSERT_GE(draws, 30);
  nees_t /= draws;
  nees_r /= draws;
  std::printf("cloud under ZED 2 noise: mean NEES centre %.2f, rotation %.2f over %d clouds\n", nees_t, nees_r, draws);
  EXPECT_GE(nees_t, 1.5);
  EXPECT_LE(nees_t, 6.0);
  EXPECT_GE(nees_r, 1.5);
  EXPECT_LE(nees_r, 6.0);
}

}  // namespace
}  // namespace arucotag

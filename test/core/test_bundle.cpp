// Marker bundles: config validation and parsing, and the joint pose of rendered posts against truth.
#include <cstdio>

#include <gtest/gtest.h>

#include "scene.hpp"

namespace arucotag {
namespace {

using test::kDeg;

constexpr double kSide = 0.15;       // m, black square of every face
constexpr double kPostWidth = 0.20;  // m, the face with its quiet zone

// A square post with a marker on each listed face (id, azimuth of the face normal in degrees from
// the bundle's x axis, counter-clockwise seen from above). Bundle frame: on the post's axis at the
// markers' centre height, z up.
MarkerBundle Post(const std::vector<std::pair<int, double>>& faces, const std::string& name = "post") {
  MarkerBundle bundle;
  bundle.name = name;
  bundle.frame = name;
  for (const auto& [id, azimuth] : faces) {
    BundleMember m;
    m.id = id;
    m.side_length = kSide;
    const double a = azimuth * kDeg;
    m.position = cv::Vec3d(std::cos(a), std::sin(a), 0.0) * (kPostWidth / 2.0);
    m.rotation = RotationFromRpy(90.0 * kDeg, 0.0, 90.0 * kDeg + a);
    bundle.members.push_back(m);
  }
  return bundle;
}

struct Pose {
  cv::Vec3d rvec, tvec;  // bundle -> camera
};

// The post at `position` (optical frame) seen from `azimuth_deg` in the bundle frame (0: straight
// at the x face), the camera `elevation_deg` above it.
Pose PostPose(const cv::Vec3d& position, double azimuth_deg, double elevation_deg) {
  const double e = elevation_deg * kDeg, a = azimuth_deg * kDeg;
  const cv::Vec3d up(0.0, -std::cos(e), std::sin(e));  // camera y down, tilted to look down at it
  cv::Vec3d towards = -cv::normalize(position);
  towards = cv::normalize(towards - towards.dot(up) * up);
  const cv::Vec3d across = up.cross(towards);
  const cv::Vec3d x = std::cos(a) * towards - std::sin(a) * across;
  const cv::Vec3d y = up.cross(x);
  const cv::Matx33d r(x[0], y[0], up[0], x[1], y[1], up[1], x[2], y[2], up[2]);
  Pose pose;
  cv::Rodrigues(r, pose.rvec);
  pose.tvec = position;
  return pose;
}

// Member -> camera from bundle -> camera, and back.
Pose Compose(const Pose& bundle, const BundleMember& m) {
  cv::Matx33d r;
  cv::Rodrigues(bundle.rvec, r);
  Pose out;
  cv::Rodrigues(r * m.rotation, out.rvec);
  out.tvec = r * m.position + bundle.tvec;
  return out;
}

Pose BundleSeenThrough(const BundleMember& m, const cv::Vec3d& rvec, const cv::Vec3d& tvec) {
  cv::Matx33d r;
  cv::Rodrigues(rvec, r);
  const cv::Matx33d rb = r * m.rotation.t();
  Pose out;
  cv::Rodrigues(rb, out.rvec);
  out.tvec = tvec - rb * m.position;
  return out;
}

std::vector<sim::Marker> Markers(const MarkerBundle& bundle, const Pose& pose) {
  std::vector<sim::Marker> markers;
  for (const auto& m : bundle.members) {
    const Pose face = Compose(pose, m);
    markers.push_back({m.id, m.side_length, face.rvec, face.tvec});
  }
  return markers;
}

struct Errors {
  double position = 0.0, rotation = 0.0;  // m, rad
};

Errors ErrorOf(const Pose& estimate, const Pose& truth) {
  return {cv::norm(estimate.tvec - truth.tvec), test::RotationError(estimate.rvec, truth.rvec)};
}

// Each detected face alone: its PnP pose with the member's size, carried to the bundle frame.
struct SingleFaces {
  Errors oracle{1e9, 1e9};  // the smallest position and the smallest rotation error over the faces
  // The face a tracker without bundles would trust most: the smallest position variance for the
  // position, the smallest rotation variance for the rotation (its own covariance, not the truth).
  Errors trusted;
};

SingleFaces EachFace(const CameraModel& camera, const MarkerBundle& bundle, const std::vector<ArucoTag>& tags,
                     const Pose& truth) {
  SingleFaces faces;
  double position_variance = 1e9, rotation_variance = 1e9;
  for (ArucoTag tag : tags) {
    for (const auto& m : bundle.members) {
      if (m.id != tag.id) continue;
      tag.side_length = m.side_length;
      if (!EstimatePoseFromPNP(camera, tag)) continue;
      const Errors e = ErrorOf(BundleSeenThrough(m, tag.rvec, tag.tvec), truth);
      faces.oracle.position = std::min(faces.oracle.position, e.position);
      faces.oracle.rotation = std::min(faces.oracle.rotation, e.rotation);
      const cv::Matx66d& c = tag.covariance;
      if (c(0, 0) + c(1, 1) + c(2, 2) < position_variance) {
        position_variance = c(0, 0) + c(1, 1) + c(2, 2);
        faces.trusted.position = e.position;
      }
      if (c(3, 3) + c(4, 4) + c(5, 5) < rotation_variance) {
        rotation_variance = c(3, 3) + c(4, 4) + c(5, 5);
        faces.trusted.rotation = e.rotation;
      }
    }
  }
  return faces;
}

std::vector<ArucoTag> See(const sim::Camera& camera, const std::vector<sim::Marker>& markers, unsigned seed) {
  DetectorConfig config;
  config.tracking = false;  // unrelated renders
  sim::RenderOptions options;
  options.seed = seed;
  options.noise_sigma = 2.0;
  options.blur_sigma = 0.6;
  return test::RenderAndDetect(camera, markers, config, options);
}

// ---- configuration ----

const char* const kTwoPosts = R"(
# comment first, as rosparam files have
bundles:
  - name: post_a   # comment
    frame: post_a_frame
    members:
      - {id: 1, size: 0.15, position: [0.1, 0.0, 0.0], rpy_deg: [90, 0, 90]}
      - id: 2
        size: 0.2
        position: [0.0, 0.1, 0.0]
        rpy_deg: [90, 0, 180]
  - name: post_b
    members:
      - {id: 3, size: 0.15}
)";

std::string ErrorOfText(const std::string& text) {
  try {
    BundlesFromText(text);
  } catch (const Error& e) {
    return e.what();
  }
  return "no error";
}

TEST(BundleConfig, ParsesNamesFramesSizesAndPoses) {
  const auto bundles = BundlesFromText(kTwoPosts);
  ASSERT_EQ(bundles.size(), 2u);
  EXPECT_EQ(bundles[0].name, "post_a");
  EXPECT_EQ(bundles[0].frame, "post_a_frame");
  EXPECT_EQ(bundles[1].frame, "post_b") << "the frame defaults to the name";
  ASSERT_EQ(bundles[0].members.size(), 2u);
  const BundleMember& second = bundles[0].members[1];
  EXPECT_EQ(second.id, 2);
  EXPECT_DOUBLE_EQ(second.side_length, 0.2);
  EXPECT_EQ(second.position, cv::Vec3d(0.0, 0.1, 0.0));
  // rpy 90 0 180: the marker's z (out of its face) along bundle +y, its x along -x, its y up.
  const cv::Matx33d expected(-1, 0, 0, 0, 0, 1, 0, 1, 0);
  EXPECT_LT(cv::norm(second.rotation - expected, cv::NORM_INF), 1e-12);
  // The top-left corner: marker (-s/2, s/2, 0) -> bundle (s/2, 0.1, s/2).
  const auto corners = second.Corners();
  EXPECT_NEAR(corners[0].x, 0.1, 1e-12);
  EXPECT_NEAR(corners[0].y, 0.1, 1e-12);
  EXPECT_NEAR(corners[0].z, 0.1, 1e-12);
  EXPECT_EQ(bundles[1].members[0].rotation, cv::Matx33d::eye()) << "rpy_deg defaults to 0 0 0";
  // JSON, as the nodelet hands over what rosparam loaded.
  const auto json = BundlesFromText(
      R"({"bundles": [{"name": "p", "members": [{"id": 9, "size": 0.2, "rpy_deg": [0, 0, 90.5]}]}]})");
  ASSERT_EQ(json.size(), 1u);
  EXPECT_EQ(json[0].members[0].id, 9);
  EXPECT_NEAR(json[0].members[0].rotation(1, 0), std::sin(90.5 * kDeg), 1e-12);
  EXPECT_NE(ErrorOfText(R"({"bundles": [{"name": "p", "members": [{"id": 9, "size": "true"}]}]})")
                .find("bundle 'p' member id 9 size must be a number"),
            std::string::npos);
  EXPECT_TRUE(BundlesFromText("bundles: []").empty());
  EXPECT_TRUE(BundlesFromText("other: 1").empty());
}

TEST(BundleConfig, TheUrcExampleLoads) {
  const auto bundles = LoadBundles(std::string(ARUCOTAG_SOURCE_DIR) + "/config/urc_bundles.yaml");
  ASSERT_FALSE(bundles.empty());
  for (const auto& b : bundles) EXPECT_GE(b.members.size(), 3u) << b.name;
}

TEST(BundleConfig, InvalidConfigsNameTheBundleAndId) {
  const std::string duplicate = ErrorOfText(R"(bundles:
  - {name: a, members: [{id: 4, size: 0.15}]}
  - {name: b, members: [{id: 5, size: 0.15}, {id: 4, size: 0.15, position: [0, 1, 0]}]})");
  EXPECT_NE(duplicate.find("bundle 'b' member id 4"), std::string::npos) << duplicate;
  EXPECT_NE(duplicate.find("also in bundle 'a'"), std::string::npos) << duplicate;

  const std::string zero = ErrorOfText("bundles:\n  - {name: a, members: [{id: 7, size: 0}]}");
  EXPECT_NE(zero.find("bundle 'a' member id 7: size must be > 0 m"), std::string::npos) << zero;
  const std::string negative = ErrorOfText("bundles:\n  - {name: a, members: [{id: 7, size: -0.15}]}");
  EXPECT_NE(negative.find("size must be > 0 m"), std::string::npos) << negative;

  const std::string copied =
      ErrorOfText("bundles:\n  - {name: a, members: [{id: 7, size: 0.15}, {id: 7, size: 0.15}]}");
  EXPECT_NE(copied.find("bundle 'a' member id 7 is listed twice at the same place"), std::string::npos) << copied;
  const std::string empty = ErrorOfText("bundles:\n  - {name: a, members: []}");
  EXPECT_NE(empty.find("bundle 'a' has no members"), std::string::npos) << empty;
  const std::string names =
      ErrorOfText("bundles:\n  - {name: a, members: [{id: 1, size: 1}]}\n  - {name: a, members: [{id: 2, size: 1}]}");
  EXPECT_NE(names.find("two bundles are named 'a'"), std::string::npos) << names;
  const std::string typo = ErrorOfText("bundles:\n  - {name: a, members: [{id: 1, size: 1, rpy: [0, 0, 1]}]}");
  EXPECT_NE(typo.find("bundle 'a' member id 1 has an unknown key 'rpy'"), std::string::npos) << typo;
  const std::string no_size = ErrorOfText("bundles:\n  - {name: a, members: [{id: 1}]}");
  EXPECT_NE(no_size.find("bundle 'a' member id 1 needs a size"), std::string::npos) << no_size;
  const std::string short_position =
      ErrorOfText("bundles:\n  - {name: a, members: [{id: 1, size: 1, position: [0, 1]}]}");
  EXPECT_NE(short_position.find("position must be a list of three numbers"), std::string::npos) << short_position;

  // Structs built in code are held to the same rules.
  MarkerBundle bundle = Post({{1, 0.0}, {2, 90.0}});
  bundle.members[1].position[2] = std::numeric_limits<double>::quiet_NaN();
  EXPECT_THROW(ValidateBundles({bundle}), Error);
  bundle = Post({{1, 0.0}});
  bundle.members[0].rotation = cv::Matx33d::diag({1.0, 1.0, -1.0});
  EXPECT_THROW(ValidateBundles({bundle}), Error);
  // A URC post prints one id on every face: allowed where the faces differ.
  EXPECT_NO_THROW(ValidateBundles({Post({{3, 0.0}, {3, 90.0}, {3, -90.0}})}));
}

// ---- pose ----

// A three-faced post at 3, 8 and 15 m, seen from random azimuths that show two faces: the joint
// pose's mean position and rotation errors are at most those of the face a tracker would trust
// most (smallest covariance), and its rotation error at most that of the luckiest face of each
// view; its covariance is consistent with its errors (mean NEES in [0.25, 2] x 3).
TEST(BundlePose, ThreeFacedPostBeatsItsBestFaceAt3And8And15m) {
  const sim::Camera sim_camera = sim::MakeCamera({1920, 1080}, 40.0);  // a mast camera zoomed for range
  const CameraModel camera = test::ToModel(sim_camera);
  const MarkerBundle post = Post({{10, 0.0}, {11, 90.0}, {12, -90.0}});
  constexpr int kViews = 12;
  for (double range : {3.0, 8.0, 15.0}) {
    Errors bundle, trusted, oracle;
    int joint = 0;
    double nees_t = 0.0, nees_r = 0.0;
    for (int view = 0; view < kViews; ++view) {
      cv::RNG rng(static_cast<uint64_t>(1000 * range + view));
      const double side = rng.uniform(0, 2) == 0 ? 1.0 : -1.0;
      const double azimuth = side * rng.uniform(25.0, 65.0);
      const cv::Vec3d position(rng.uniform(-0.2, 0.2) * range, rng.uniform(-0.05, 0.05) * range, range);
      const Pose truth = PostPose(position, azimuth, rng.uniform(-5.0, 10.0));
      const auto tags = See(sim_camera, Markers(post, truth), static_cast<unsigned>(view + 1));
      const BundlePose estimate = EstimateBundlePose(camera, post, tags);
      ASSERT_TRUE(estimate.valid) << range << " m, view " << view;
      const Errors b = ErrorOf({estimate.rvec, estimate.tvec}, truth);
      const SingleFaces s = EachFace(camera, post, tags, truth);
      EXPECT_LT(b.rotation, 1.0 * kDeg) << range << " m, view " << view;
      EXPECT_LT(b.position, 0.005 * range) << range << " m, view " << view;
      for (auto [sum, e] : {std::make_pair(&bundle, b), std::make_pair(&trusted, s.trusted),
                            std::make_pair(&oracle, s.oracle)}) {
        sum->position += e.position / kViews;
        sum->rotation += e.rotation / kViews;
      }
      joint += estimate.member_ids.size() >= 2;
      nees_t += test::Nees(estimate.covariance, 0, estimate.tvec - truth.tvec) / kViews;
      nees_r += test::Nees(estimate.covariance, 3, test::RotationResidual(estimate.rvec, truth.rvec)) / kViews;
    }
    // The corner-noise prior calibrated for lone faces (PnP's NEES) outweighs the joint residual
    // on these clean renders: the covariance errs on the safe side, by up to 3x in variance.
    std::printf("%4.0f m: bundle mean NEES translation %.2f, rotation %.2f (3 expected)\n", range, nees_t, nees_r);
    EXPECT_GT(nees_t, 0.75) << range << " m";
    EXPECT_LT(nees_t, 6.0) << range << " m";
    EXPECT_GT(nees_r, 0.75) << range << " m";
    EXPECT_LT(nees_r, 6.0) << range << " m";
    std::printf("%4.0f m, mean of %d views (%d with two faces): bundle %.2f mm %.4f deg, most trusted face %.2f mm "
                "%.4f deg, luckiest face %.2f mm %.4f deg\n",
                range, kViews, joint, 1e3 * bundle.position, bundle.rotation / kDeg, 1e3 * trusted.position,
                trusted.rotation / kDeg, 1e3 * oracle.position, oracle.rotation / kDeg);
    EXPECT_GE(joint, kViews / 2) << range << " m: too few views used two faces";
    EXPECT_LE(bundle.position, trusted.position) << range << " m";
    EXPECT_LE(bundle.rotation, trusted.rotation) << range << " m";
    EXPECT_LE(bundle.rotation, oracle.rotation) << range << " m";
  }
}

// A two-faced post turned so that one face is 78 degrees off the line of sight (the steepest the
// detector still finds here): the edge-on face joins the pose and must not spoil it (its corners
// are poorly placed along the foreshortened side; a wrong match or a bad start would show as a
// pose degrees off).
TEST(BundlePose, TwoFacedPostWithOneFaceEdgeOn) {
  const sim::Camera sim_camera = test::RoverCamera();
  const CameraModel camera = test::ToModel(sim_camera);
  const MarkerBundle post = Post({{20, 0.0}, {21, 90.0}});
  for (double range : {2.0, 5.0}) {
    const Pose truth = PostPose({0.3, 0.1, range}, 12.0, 5.0);  // face 20 at 12 degrees, face 21 at 78
    const auto tags = See(sim_camera, Markers(post, truth), 3);
    const BundlePose estimate = EstimateBundlePose(camera, post, tags);
    ASSERT_TRUE(estimate.valid);
    EXPECT_EQ(estimate.member_ids, (std::vector<int>{20, 21})) << range << " m: the edge-on face must be matched";
    const Errors b = ErrorOf({estimate.rvec, estimate.tvec}, truth);
    Errors edge_on{1e9, 1e9};
    for (ArucoTag tag : tags) {
      if (tag.id == 21 && EstimatePoseFromPNP(camera, tag)) {
        edge_on = ErrorOf(BundleSeenThrough(post.members[1], tag.rvec, tag.tvec), truth);
      }
    }
    std::printf("%.0f m, one face at 78 deg: bundle %.2f mm %.4f deg, that face alone %.2f mm %.4f deg\n", range,
                1e3 * b.position, b.rotation / kDeg, 1e3 * edge_on.position, edge_on.rotation / kDeg);
    EXPECT_LT(b.position, 0.001 * range);
    EXPECT_LT(b.rotation, 0.1 * kDeg);
  }
}

// Only the front face in view (the others turned away): the pose comes from it alone, and the
// reported member, tag index, error and covariance are that face's.
TEST(BundlePose, OneVisibleMemberStillGivesThePose) {
  const sim::Camera sim_camera = test::RoverCamera();
  const CameraModel camera = test::ToModel(sim_camera);
  const MarkerBundle post = Post({{30, 0.0}, {31, 90.0}, {32, -90.0}});
  const Pose truth = PostPose({-0.2, 0.05, 4.0}, 0.0, 3.0);
  std::vector<sim::Marker> markers = Markers(post, truth);
  markers.push_back(sim::FacingCamera(5, 0.15, {0.6, 0.0, 4.0}));  // not a member
  const auto tags = See(sim_camera, markers, 4);
  ASSERT_EQ(tags.size(), 2u);
  const BundlePose estimate = EstimateBundlePose(camera, post, tags);
  ASSERT_TRUE(estimate.valid);
  EXPECT_EQ(estimate.member_ids, std::vector<int>{30});
  ASSERT_EQ(estimate.tags.size(), 1u);
  EXPECT_EQ(tags[estimate.tags[0]].id, 30);
  EXPECT_EQ(estimate.pose_source, PoseSource::kPnp);
  const Errors b = ErrorOf({estimate.rvec, estimate.tvec}, truth);
  EXPECT_LT(b.position, 0.01);
  EXPECT_LT(b.rotation, 1.0 * kDeg);

  ArucoTag face = tags[estimate.tags[0]];
  ASSERT_TRUE(EstimatePoseFromPNP(camera, face));
  EXPECT_NEAR(estimate.reprojection_error, face.pnp.rms[0], 1e-9);
  // The bundle origin sits 0.1 m behind the face: its position variance along the line of sight
  // matches the face's, and its rotation block is the face's (one rigid body).
  for (int i = 3; i < 6; ++i) EXPECT_NEAR(estimate.covariance(i, i), face.covariance(i, i), 1e-3 * face.covariance(i, i));
  EXPECT_GT(estimate.covariance(2, 2), 0.0);

  // No member in view: no pose.
  EXPECT_FALSE(EstimateBundlePose(camera, post, {tags[estimate.tags[0] == 0 ? 1 : 0]}).valid);
}

// One face, far and near frontal, whose corners prefer the flipped solution (they are the flip's
// projection: noise can do this): the cloud's plane brings the bundle back, as it does the tag.
TEST(BundlePose, CloudResolvesTheFlipOfASingleFace) {
  const sim::Camera sim_camera = test::RoverCamera();
  const CameraModel camera = test::ToModel(sim_camera);
  const MarkerBundle post = Post({{40, 0.0}, {41, 90.0}});
  const Pose truth = PostPose({0.2, 0.1, 6.0}, -20.0, 0.0);  // face 40 at 20 degrees, face 41 away
  const sim::Marker front = Markers(post, truth)[0];

  ArucoTag exact;
  exact.id = 40;
  exact.side_length = kSide;
  exact.corners = sim::ProjectCorners(sim_camera, front);
  ASSERT_TRUE(EstimatePoseFromPNP(camera, exact));
  ASSERT_EQ(exact.pnp.solutions, 2);
  const sim::Marker flip{40, kSide, exact.pnp.rvec[1], exact.pnp.tvec[1]};
  ArucoTag tag = exact;
  tag.pnp = PnpResult();
  tag.corners = sim::ProjectCorners(sim_camera, flip);

  const BundlePose corners_only = EstimateBundlePose(camera, post, {tag});
  ASSERT_TRUE(corners_only.valid);
  EXPECT_GT(ErrorOf({corners_only.rvec, corners_only.tvec}, truth).rotation, 10.0 * kDeg)
      << "the corners alone must pick the flip for this test to mean anything";

  cv::Mat depth;
  sim::RenderScene(sim_camera, {front}, sim::RenderOptions(), &depth);
  const cv::Mat cloud = sim::MakeOrganizedCloud(sim_camera, depth, sim::CloudOptions());
  CloudPoseOptions clean;
  clean.depth_noise_per_m2 = 0.0;  // a noiseless cloud
  ASSERT_TRUE(EstimatePoseFromPointCloud(cloud, sim_camera.size, tag, clean));
  const BundlePose fused = EstimateBundlePose(camera, post, {tag});
  ASSERT_TRUE(fused.valid);
  EXPECT_EQ(fused.pose_source, PoseSource::kFused);
  const Errors e = ErrorOf({fused.rvec, fused.tvec}, truth);
  EXPECT_LT(e.rotation, 2.0 * kDeg);
  EXPECT_LT(e.position, 0.03);
}

// A URC post prints one id on all three faces: each detection is matched to the face its position
// fits, and the pose uses both visible faces.
TEST(BundlePose, OneIdOnEveryFaceIsMatchedByPosition) {
  const sim::Camera sim_camera = test::RoverCamera();
  const CameraModel camera = test::ToModel(sim_camera);
  const MarkerBundle post = Post({{7, 0.0}, {7, 90.0}, {7, -90.0}});
  const Pose truth = PostPose({0.1, 0.1, 3.0}, 40.0, 5.0);  // the x face and the +y face
  const auto tags = See(sim_camera, Markers(post, truth), 5);
  ASSERT_EQ(tags.size(), 2u);
  const BundlePose estimate = EstimateBundlePose(camera, post, tags);
  ASSERT_TRUE(estimate.valid);
  EXPECT_EQ(estimate.member_ids, (std::vector<int>{7, 7}));
  // Which two adjacent faces these are is the post's own symmetry (a quarter turn about its axis
  // swaps them): the axis' position and its direction are what the faces fix.
  EXPECT_LT(cv::norm(estimate.tvec - truth.tvec), 0.01);
  cv::Matx33d r, t;
  cv::Rodrigues(estimate.rvec, r);
  cv::Rodrigues(truth.rvec, t);
  const cv::Vec3d axis(r(0, 2), r(1, 2), r(2, 2)), true_axis(t(0, 2), t(1, 2), t(2, 2));
  EXPECT_LT(std::acos(std::min(1.0, axis.dot(true_axis))), 1.0 * kDeg);
}

}  // namespace
}  // namespace arucotag

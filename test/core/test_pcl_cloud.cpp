// The cloud pose from a pcl::PointCloud, and the PCL plane fit's rejection of background points.
#include <gtest/gtest.h>

#include <algorithm>
#include <limits>
#include <utility>
#include <vector>

#include <opencv2/imgproc.hpp>
#include <pcl/point_cloud.h>
#include <pcl/point_types.h>

#include "plane_fit.hpp"
#include "scene.hpp"

namespace arucotag {
namespace {

using test::kDeg;

// The marker rendered by the rover camera, detected, and its organized cloud with a ZED 2's stereo
// noise into `cloud` (CV_32FC3).
ArucoTag DetectWithCloud(const sim::Marker& marker, cv::Mat& cloud) {
  const sim::Camera camera = test::RoverCamera();
  cv::Mat depth;
  const cv::Mat image = sim::RenderScene(camera, {marker}, sim::RenderOptions(), &depth);
  sim::CloudOptions options;
  options.stereo = sim::DepthNoise::Zed2();
  options.seed = 5;
  cloud = sim::MakeOrganizedCloud(camera, depth, options, image);
  cv::Mat grey;
  PreprocessFrame(image, grey);
  const auto tags = Detect(grey, Detector());
  EXPECT_EQ(tags.size(), 1u);
  return tags.empty() ? ArucoTag() : tags[0];
}

pcl::PointCloud<pcl::PointXYZ> ToPcl(const cv::Mat& cloud) {
  pcl::PointCloud<pcl::PointXYZ> out(static_cast<uint32_t>(cloud.cols), static_cast<uint32_t>(cloud.rows));
  for (int v = 0; v < cloud.rows; ++v) {
    for (int u = 0; u < cloud.cols; ++u) {
      const cv::Vec3f& p = cloud.at<cv::Vec3f>(v, u);
      out.at(u, v) = pcl::PointXYZ(p[0], p[1], p[2]);
    }
  }
  return out;
}

cv::Vec3d Normal(const cv::Vec3d& rvec) {
  cv::Matx33d r;
  cv::Rodrigues(rvec, r);
  return {r(0, 2), r(1, 2), r(2, 2)};
}

TEST(PclCloud, GivesTheSamePoseAsTheMatCloud) {
  const sim::Marker marker = sim::FacingCamera(4, 0.15, {0.3, -0.1, 2.5}, 30.0, 10.0, 20.0);
  cv::Mat cloud;
  const ArucoTag detected = DetectWithCloud(marker, cloud);
  ArucoTag from_mat = detected, from_pcl = detected;
  ASSERT_TRUE(EstimatePoseFromPointCloud(cloud, cloud.size(), from_mat));
  ASSERT_TRUE(EstimatePoseFromPointCloud(ToPcl(cloud), from_pcl));
  ASSERT_TRUE(from_pcl.cloud.has_rotation);
  // The same points in the same order: the same numbers.
  EXPECT_EQ(from_pcl.cloud.points, from_mat.cloud.points);
  EXPECT_EQ(from_pcl.pose_source, PoseSource::kPointCloud);
  for (int i = 0; i < 3; ++i) {
    EXPECT_DOUBLE_EQ(from_pcl.tvec[i], from_mat.tvec[i]) << i;
    EXPECT_DOUBLE_EQ(from_pcl.rvec[i], from_mat.rvec[i]) << i;
  }
  EXPECT_DOUBLE_EQ(from_pcl.cloud.plane_rms, from_mat.cloud.plane_rms);
  // And both are the marker.
  EXPECT_NEAR(from_pcl.distance, cv::norm(marker.tvec), 0.01);
  EXPECT_GT(from_pcl.cloud.normal.dot(Normal(marker.rvec)), std::cos(5.0 * kDeg));
}

TEST(PclCloud, RejectsACloudThatIsNotAnImage) {
  ArucoTag tag;
  tag.corners = {cv::Point2f(10, 10), cv::Point2f(20, 10), cv::Point2f(20, 20), cv::Point2f(10, 20)};
  const pcl::PointCloud<pcl::PointXYZ> row(640 * 480, 1, pcl::PointXYZ(0.f, 0.f, 1.f));
  EXPECT_THROW(EstimatePoseFromPointCloud(row, tag), Error);
  pcl::PointCloud<pcl::PointXYZ> short_of_points(640, 480, pcl::PointXYZ(0.f, 0.f, 1.f));
  short_of_points.points.resize(1000);
  EXPECT_THROW(EstimatePoseFromPointCloud(short_of_points, tag), Error);
  const float nan = std::numeric_limits<float>::quiet_NaN();
  EXPECT_FALSE(EstimatePoseFromPointCloud(pcl::PointCloud<pcl::PointXYZ>(640, 480, pcl::PointXYZ(nan, nan, nan)), tag));
}

// Stereo matching fattens a near object's edge on one side: there the cloud holds the background.
// A fifth of the points the pose uses, the strip along the tag's right edge, come from a wall 1 m
// behind it. The plane fit must take the tag's face, not a plane tilted towards the wall.
TEST(PclCloud, BackgroundAtTheTagsEdgeIsRejected) {
  const sim::Marker marker = sim::FacingCamera(4, 0.15, {0.2, 0.1, 2.0}, 25.0, 0.0, 0.0);
  cv::Mat cloud;
  const ArucoTag detected = DetectWithCloud(marker, cloud);
  const CloudPoseOptions options;
  const std::vector<cv::Point2f> quad(detected.corners.begin(), detected.corners.end());
  const cv::Matx33d to_marker = cv::getPerspectiveTransform(
      quad, std::vector<cv::Point2f>{{-0.5f, 0.5f}, {0.5f, 0.5f}, {0.5f, -0.5f}, {-0.5f, -0.5f}});
  const double limit = 0.5 * (1.0 - options.shrink);
  std::vector<std::pair<double, cv::Point>> used;  // (a, pixel) of the points the pose uses
  for (int v = 0; v < cloud.rows; ++v) {
    for (int u = 0; u < cloud.cols; ++u) {
      const cv::Vec3d m = to_marker * cv::Vec3d(u, v, 1.0);
      const double a = m[0] / m[2], b = m[1] / m[2];
      if (std::abs(a) <= limit && std::abs(b) <= limit && std::isfinite(cloud.at<cv::Vec3f>(v, u)[2])) {
        used.push_back({a, cv::Point(u, v)});
      }
    }
  }
  ASSERT_GT(used.size(), 1000u);
  std::sort(used.begin(), used.end(), [](const auto& x, const auto& y) { return x.first > y.first; });
  const size_t moved = used.size() / 5;
  for (size_t i = 0; i < moved; ++i) {
    cv::Vec3f& p = cloud.at<cv::Vec3f>(used[i].second);
    p *= static_cast<float>(1.0 + 1.0 / cv::norm(p));
  }
  const cv::Vec3d normal_truth = Normal(marker.rvec);

  ArucoTag tag = detected;
  ASSERT_TRUE(EstimatePoseFromPointCloud(ToPcl(cloud), tag, options));
  ASSERT_TRUE(tag.cloud.has_normal);
  EXPECT_LT(cv::norm(tag.cloud.centre - marker.tvec), 0.01);
  EXPECT_GT(tag.cloud.normal.dot(normal_truth), std::cos(3.0 * kDeg));
  EXPECT_LE(tag.cloud.points, static_cast<int>(used.size() - moved));
  EXPECT_LT(tag.cloud.plane_rms, 0.01);

  // The least-squares fit with residual trimming (before PCL) is dragged towards the wall: the scene
  // tells the two apart.
  CloudPoseOptions legacy = options;
  legacy.plane_fit = PlaneFit::kLegacy;
  ArucoTag dragged = detected;
  ASSERT_TRUE(EstimatePoseFromPointCloud(cloud, cloud.size(), dragged, legacy));
  EXPECT_GT(cv::norm(dragged.cloud.centre - marker.tvec), 0.05);
}

// A 10x10 grid over the marker, its left half on the plane z = 2 m and its right half on a parallel
// plane `gap` behind: the consensus finds one of the two, and which one depends on the samples it
// draws.
std::vector<internal::Sample> TwoHalves(double gap) {
  std::vector<internal::Sample> samples;
  for (int i = 0; i < 10; ++i) {
    for (int j = 0; j < 10; ++j) {
      const double a = (i + 0.5) / 10.0 - 0.5, b = (j + 0.5) / 10.0 - 0.5;
      samples.push_back({a, b, cv::Vec3d(0.15 * a, 0.15 * b, a < 0.0 ? 2.0 : 2.0 + gap)});
    }
  }
  return samples;
}

constexpr PlaneFit kConsensusFits[] = {PlaneFit::kRansac, PlaneFit::kMsac, PlaneFit::kLmeds, PlaneFit::kMlesac};

CloudPoseOptions ConsensusOptions(PlaneFit method, int min_plane_points) {
  CloudPoseOptions options;
  options.plane_fit = method;
  options.min_plane_points = min_plane_points;
  return options;
}

TEST(PlaneConsensus, SameSamplesSameAnswerWhateverCameBefore) {
  // The thread's PCL model and estimators are made once and reused: each fit starts the sampler
  // from the same state, or a tag's answer would depend on the tags fitted before it.
  const std::vector<internal::Sample> samples = TwoHalves(0.3);
  for (const PlaneFit method : kConsensusFits) {
    const CloudPoseOptions options = ConsensusOptions(method, 10);
    internal::MarkerPlane first;
    ASSERT_TRUE(internal::FitMarkerPlane(samples, options, first)) << static_cast<int>(method);
    for (int run = 0; run < 6; ++run) {
      internal::MarkerPlane again;
      ASSERT_TRUE(internal::FitMarkerPlane(samples, options, again));
      EXPECT_EQ(again.use, first.use) << "method " << static_cast<int>(method) << ", run " << run;
      EXPECT_EQ(again.c, first.c) << "method " << static_cast<int>(method) << ", run " << run;
    }
  }
}

TEST(PlaneConsensus, NoModelIsAFailureNotThePreviousTagsPlane) {
  // PCL's estimators keep the last model they found and return it when no sample of the next
  // points gives one; ours forget it.
  CloudPoseOptions options;
  options.min_plane_points = 10;
  internal::MarkerPlane plane;
  ASSERT_TRUE(internal::FitMarkerPlane(TwoHalves(0.0), options, plane));
  // Every point on one line across the previous plane: no three of them span a plane, and all of
  // them lie in the previous one.
  std::vector<internal::Sample> line = TwoHalves(0.0);
  for (auto& s : line) s.xyz = cv::Vec3d(0.15 * s.a + 0.015 * s.b, 0.0, 2.0);
  EXPECT_FALSE(internal::FitMarkerPlane(line, options, plane));
}

TEST(PlaneConsensus, FewerThanThreeSamplesAreNoPlaneWhateverTheMinimum) {
  // A minimum of zero points (the fuzzer sets it) must not let an empty or two-point set through.
  const std::vector<internal::Sample> all = TwoHalves(0.0);
  for (const PlaneFit method : kConsensusFits) {
    const CloudPoseOptions options = ConsensusOptions(method, 0);
    for (size_t n = 0; n < 3; ++n) {
      internal::MarkerPlane plane;
      EXPECT_FALSE(internal::FitMarkerPlane({all.begin(), all.begin() + n}, options, plane))
          << "method " << static_cast<int>(method) << ", " << n << " samples";
    }
  }
}

}  // namespace
}  // namespace arucotag

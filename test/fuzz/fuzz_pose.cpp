// libFuzzer harness: the pose functions with arbitrary camera models, corners and clouds. K and
// the distortion take NaN, inf, zero, negative and huge values and every coefficient count; clouds
// any size and type, holes, inf. EstimatePoseFromPNP, EstimatePoseFromPointCloud, ResolvePose and
// FusedChoice must return or throw arucotag::Error (their documented answer to invalid input),
// and ResolvePose and FusedChoice must also take tags whose PnP and cloud results are arbitrary.
#include <cstddef>
#include <cstdint>
#include <vector>

#include <arucotag/pose.hpp>

#include "fuzz_input.hpp"

namespace {

using arucotag::fuzz::FuzzInput;

// The counts CameraModel accepts and their neighbours.
const int kDistortionCounts[] = {0, 4, 5, 8, 12, 14, 1, 3, 6, 13, 15};
const arucotag::PoseSource kSources[] = {arucotag::PoseSource::kNone, arucotag::PoseSource::kPnp,
                                         arucotag::PoseSource::kPointCloud, arucotag::PoseSource::kFused};

arucotag::CameraModel Camera(FuzzInput& in) {
  arucotag::CameraModel camera;
  // A plausible 640x480 pinhole unless the bytes say otherwise, so the solvers get exercised too.
  camera.K = cv::Matx33d(500, 0, 320, 0, 500, 240, 0, 0, 1);
  const std::uint8_t which = in.Byte();
  for (int i = 0; i < 9; ++i) {
    if (which & (1 << (i % 8))) camera.K.val[i] = in.Double(camera.K.val[i] == 0.0 ? 1.0 : camera.K.val[i]);
  }
  const std::uint8_t kind = in.Byte();
  camera.distortion_model = (kind & 1) ? arucotag::DistortionModel::kEquidistant
                                       : arucotag::DistortionModel::kRadialTangential;
  camera.distortion.resize(kDistortionCounts[(kind >> 1) % (sizeof(kDistortionCounts) / sizeof(int))]);
  for (auto& d : camera.distortion) d = in.Double(0.1);
  if (kind & 0x80) {
    camera.pixels.scale = cv::Vec2d(in.Double(2.0), in.Double(2.0));
    camera.pixels.offset = cv::Vec2d(in.Double(100.0), in.Double(100.0));
  }
  return camera;
}

// A tag whose corners are a square around (320, 240) moved by the bytes, or anything at all.
arucotag::ArucoTag Tag(FuzzInput& in) {
  arucotag::ArucoTag tag;
  tag.id = 0;
  const float half = static_cast<float>(in.Int(0, 300));
  const cv::Point2f square[4] = {{-half, -half}, {half, -half}, {half, half}, {-half, half}};
  const std::uint8_t wild = in.Byte();
  for (int i = 0; i < 4; ++i) {
    tag.corners[i] = cv::Point2f(320, 240) + square[i];
    if (wild & (1 << i)) tag.corners[i] = cv::Point2f(in.Double(320), in.Double(240));
    if (wild & (16 << i)) tag.corners[i] += cv::Point2f(in.Int(-8, 8) / 4.f, in.Int(-8, 8) / 4.f);
  }
  tag.side_length = (in.Byte() & 1) ? in.Double(0.15) : 0.15;
  return tag;
}

cv::Mat Cloud(FuzzInput& in, cv::Size& image_size) {
  const std::uint8_t kind = in.Byte();
  image_size = cv::Size(in.Int(0, 64), in.Int(0, 48));
  cv::Size size = image_size;
  if (kind & 1) size = cv::Size(in.Int(0, 64), in.Int(0, 48));
  const int type = (kind & 2) ? ((kind & 4) ? CV_32FC1 : CV_64FC3) : CV_32FC3;
  cv::Mat cloud(size, type);
  // A plane at 1-2 m, so the fit runs; then holes, inf and arbitrary points where the bytes say.
  const double z0 = 1.0 + in.Byte() / 255.0, tilt = in.Int(-100, 100) / 100.0;
  for (int v = 0; v < cloud.rows; ++v) {
    for (int u = 0; u < cloud.cols; ++u) {
      const double z = z0 + tilt * (u - size.width / 2.0) / std::max(1, size.width);
      const double x = (u - size.width / 2.0) * z / 50.0, y = (v - size.height / 2.0) * z / 50.0;
      const std::uint8_t noise = in.Byte();
      double p[3] = {x, y, z};
      if (noise >= 0xc0) {
        for (double& c : p) c = in.Double(z);
      }
      if (type == CV_32FC3) {
        cloud.at<cv::Vec3f>(v, u) = cv::Vec3f(static_cast<float>(p[0]), static_cast<float>(p[1]), static_cast<float>(p[2]));
      } else if (type == CV_64FC3) {
        cloud.at<cv::Vec3d>(v, u) = cv::Vec3d(p[0], p[1], p[2]);
      } else {
        cloud.at<float>(v, u) = static_cast<float>(p[2]);
      }
    }
  }
  return cloud;
}

// Arbitrary PnP and cloud results, for ResolvePose and FusedChoice on their own.
void ArbitraryResults(FuzzInput& in, arucotag::ArucoTag& tag) {
  auto& pnp = tag.pnp;
  pnp.valid = in.Bool();
  pnp.solutions = in.Int(-1, 3);
  for (int i = 0; i < 2; ++i) {
    pnp.rvec[i] = cv::Vec3d(in.Double(), in.Double(), in.Double());
    pnp.tvec[i] = cv::Vec3d(in.Double(), in.Double(), in.Double(2.0));
    pnp.rms[i] = in.Double(0.5);
    for (double& c : pnp.covariance[i].val) c = (in.Byte() & 1) ? in.Double(1e-4) : 0.0;
  }
  pnp.ambiguity = in.Double(0.5);
  pnp.corner_sigma = in.Double(0.1);
  auto& cloud = tag.cloud;
  cloud.valid = in.Bool();
  cloud.points = in.Int(-10, 5000);
  cloud.centre = cv::Vec3d(in.Double(), in.Double(), in.Double(2.0));
  cloud.has_normal = in.Bool();
  cloud.normal = cv::Vec3d(in.Double(), in.Double(), in.Double(-1.0));
  cloud.has_rotation = in.Bool();
  for (double& c : cloud.rotation.val) c = in.Double();
  cloud.plane_rms = in.Double(0.01);
  cloud.normal_sigma = in.Double(0.1);
  for (double& c : cloud.covariance.val) c = (in.Byte() & 1) ? in.Double(1e-4) : 0.0;
}

}  // namespace

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  FuzzInput in(data, size);
  const std::uint8_t mode = in.Byte();
  const arucotag::CameraModel camera = Camera(in);
  arucotag::ArucoTag tag = Tag(in);
  try {
    camera.Validate();
    std::vector<cv::Point2d> corners(tag.corners.begin(), tag.corners.end());
    (void)camera.Normalize(corners);
  } catch (const arucotag::Error&) {
  }
  cv::Size image_size;
  const cv::Mat cloud = Cloud(in, image_size);
  arucotag::CloudPoseOptions options;
  if (mode & 1) {
    options.shrink = in.Double(0.15);
    options.min_points = in.Int(-5, 100);
    options.min_plane_points = in.Int(-5, 100);
    options.max_samples = in.Int(-5, 5000);
    options.depth_noise_per_m2 = in.Double(0.002);
  }
  // The cloud's pixels are the image's: scale the corners from the 640x480 camera onto it.
  arucotag::ArucoTag cloud_tag = tag;
  for (auto& c : cloud_tag.corners) c = cv::Point2f(c.x * image_size.width / 640.f, c.y * image_size.height / 480.f);
  try {
    if (mode & 2) {
      arucotag::EstimatePoseFromPointCloud(cloud, image_size, cloud_tag, options);
      tag.cloud = cloud_tag.cloud;
    }
    arucotag::EstimatePoseFromPNP(camera, tag);
    if (!(mode & 2)) arucotag::EstimatePoseFromPointCloud(cloud, image_size, cloud_tag, options);
  } catch (const arucotag::Error&) {
  }
  for (const auto source : kSources) arucotag::ResolvePose(tag, source);
  (void)arucotag::FusedChoice(tag);

  ArbitraryResults(in, tag);
  (void)arucotag::FusedChoice(tag);
  for (const auto source : kSources) arucotag::ResolvePose(tag, source);
  return 0;
}

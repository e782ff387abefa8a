// Shared helpers of the core tests: a rover-like camera and rendered scenes with known truth.
#pragma once

#include <cmath>
#include <vector>

#include <gtest/gtest.h>
#include <opencv2/calib3d.hpp>
#include <opencv2/imgcodecs.hpp>

#include <arucotag/arucotag.hpp>
#include <arucotag/sim.hpp>

namespace arucotag::test {

inline constexpr double kDeg = M_PI / 180.0;

/// 1280x720 with a 65 degree horizontal field of view (fx about 1005 px), like a rover mast camera.
inline sim::Camera RoverCamera(bool distorted = false) {
  sim::Camera camera = sim::MakeCamera({1280, 720}, 65.0);
  if (distorted) camera.dist = {-0.12, 0.03, 0.0005, -0.0004, 0.0};
  return camera;
}

/// The model of a render: its exact intrinsics, and no corner error of the camera's own (no lens
/// model residual, no compression; see CameraModel::corner_noise).
inline CameraModel ToModel(const sim::Camera& camera) {
  CameraModel model = CameraModel::FromIntrinsics(camera.K, camera.dist);
  model.corner_noise = 0.0;
  return model;
}

/// Angle (rad) of the rotation taking one Rodrigues rotation to the other.
inline double RotationError(const cv::Vec3d& a, const cv::Vec3d& b) {
  cv::Matx33d ra, rb;
  cv::Rodrigues(a, ra);
  cv::Rodrigues(b, rb);
  const cv::Matx33d d = ra.t() * rb;
  const double c = std::max(-1.0, std::min(1.0, (cv::trace(d) - 1.0) / 2.0));
  return std::acos(c);
}

/// Small rotation (rad, about the camera axes) taking the truth to the estimate: R_est = exp([e]x) R_true.
inline cv::Vec3d RotationResidual(const cv::Vec3d& estimate, const cv::Vec3d& truth) {
  cv::Matx33d re, rt;
  cv::Rodrigues(estimate, re);
  cv::Rodrigues(truth, rt);
  cv::Vec3d e;
  cv::Rodrigues(re * rt.t(), e);
  return e;
}

/// e^T C^-1 e for the 3x3 block of `covariance` starting at `first`.
inline double Nees(const PoseCovariance& covariance, int first, const cv::Vec3d& e) {
  const cv::Matx33d block = covariance.get_minor<3, 3>(first, first);
  return e.dot(block.inv(cv::DECOMP_CHOLESKY) * e);
}

/// Renders the markers as the grey image the detector takes.
inline cv::Mat RenderGrey(const sim::Camera& camera, const std::vector<sim::Marker>& markers,
                          const sim::RenderOptions& options) {
  cv::Mat grey;
  PreprocessFrame(sim::RenderScene(camera, markers, options), grey);
  return grey;
}

/// Renders the markers and runs the default detector (sub-pixel corners) on the grey image.
inline std::vector<ArucoTag> RenderAndDetect(const sim::Camera& camera, const std::vector<sim::Marker>& markers,
                                             DetectorConfig config = {}, sim::RenderOptions options = {}) {
  options.dictionary = DictionaryFromName(config.dictionary);
  return Detect(RenderGrey(camera, markers, options), Detector(config));
}

/// A photo from test/data as the grey image the detector takes.
inline cv::Mat LoadGrey(const std::string& relative) {
  const cv::Mat image = cv::imread(std::string(ARUCOTAG_TEST_DATA) + "/" + relative, cv::IMREAD_UNCHANGED);
  EXPECT_FALSE(image.empty()) << relative;
  cv::Mat grey;
  PreprocessFrame(image, grey);
  return grey;
}

}  // namespace arucotag::test

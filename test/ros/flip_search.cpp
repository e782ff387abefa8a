#include "flip_search.hpp"

#include <opencv2/calib3d.hpp>

#include <arucotag/arucotag.hpp>

namespace arucotag::test {

namespace {

double AngleDeg(const cv::Vec3d& a, const cv::Vec3d& b) {
  cv::Matx33d ra, rb;
  cv::Rodrigues(a, ra);
  cv::Rodrigues(b, rb);
  const double c = std::max(-1.0, std::min(1.0, (cv::trace(ra.t() * rb) - 1.0) / 2.0));
  return std::acos(c) * 180.0 / CV_PI;
}

}  // namespace

bool PnpPicksMirror(const sim::Camera& camera, const sim::Marker& marker, const cv::Mat& image) {
  cv::Mat grey;
  PreprocessFrame(image, grey);
  auto tags = Detect(grey, Detector());
  if (tags.size() != 1 || tags[0].id != marker.id) return false;
  if (!EstimatePoseFromPNP(CameraModel::FromIntrinsics(camera.K, camera.dist), tags[0])) return false;
  const PnpResult& pnp = tags[0].pnp;
  return pnp.solutions == 2 && AngleDeg(pnp.rvec[0], marker.rvec) > 10.0 && AngleDeg(pnp.rvec[1], marker.rvec) < 2.0;
}

}  // namespace arucotag::test

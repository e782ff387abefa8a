#include <arucotag/aruco_tag.hpp>

#include <cmath>

namespace arucotag {

const char* PoseSourceName(PoseSource source) {
  switch (source) {
    case PoseSource::kPnp:
      return "pnp";
    case PoseSource::kPointCloud:
      return "point_cloud";
    case PoseSource::kFused:
      return "fused";
    case PoseSource::kNone:
      break;
  }
  return "none";
}

cv::Point2f FindTagCenter(const ArucoTag& tag) {
  const auto& c = tag.corners;
  const cv::Point2d mean = (cv::Point2d(c[0]) + cv::Point2d(c[1]) + cv::Point2d(c[2]) + cv::Point2d(c[3])) * 0.25;
  // Diagonals c0 + s (c2 - c0) and c1 + t (c3 - c1); solve for s and t.
  const cv::Point2d p(c[0]), r = cv::Point2d(c[2]) - p;
  const cv::Point2d q(c[1]), d = cv::Point2d(c[3]) - q;
  const double denom = r.cross(d);
  const double scale = std::max(r.dot(r), d.dot(d));
  if (!(scale > 0.0) || std::abs(denom) < 1e-9 * scale) {
    return mean;
  }
  const double s = (q - p).cross(d) / denom;
  const double t = (q - p).cross(r) / denom;
  // A convex quad's diagonals cross strictly inside both segments; otherwise the quad is folded.
  if (!(s > 0.0 && s < 1.0 && t > 0.0 && t < 1.0)) {
    return mean;
  }
  return cv::Point2f(p + s * r);
}

}  // namespace arucotag

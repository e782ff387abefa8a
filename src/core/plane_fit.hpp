// The marker-plane fit of EstimatePoseFromPointCloud (internal to arucotag_core).
#pragma once

#include <vector>

#include <opencv2/core.hpp>

#include <arucotag/pose.hpp>

namespace arucotag::internal {

/// One cloud point on the tag.
struct Sample {
  double a, b;    ///< marker-plane coordinates of its pixel, in side lengths, origin at the centre
  cv::Vec3d xyz;  ///< the cloud point (m, optical frame)
};

/// The marker plane as xyz = c + a * ex + b * ey, and which samples it was fitted to.
struct MarkerPlane {
  cv::Vec3d c, ex, ey;
  std::vector<char> use;  ///< 1 for the inliers, one entry per sample
};

/// Least-squares fit of xyz = c + a * ex + b * ey to the samples `use` marks: exact for a plane seen
/// through a pinhole, because (a, b) come from the image-to-marker homography. Returns false when the
/// system is singular or the result is not finite.
bool FitAffine(const std::vector<Sample>& samples, const std::vector<char>& use, cv::Vec3d& c, cv::Vec3d& ex,
               cv::Vec3d& ey);

/// Fits the marker plane to the samples robustly, as options.plane_fit says (see PlaneFit), and
/// refines it by FitAffine on the inliers. Returns false when fewer than options.min_plane_points
/// inliers remain or the fit is singular (plane left unspecified).
bool FitMarkerPlane(const std::vector<Sample>& samples, const CloudPoseOptions& options, MarkerPlane& plane);

/// The median (upper median for an even count) of a non-empty list.
double Median(std::vector<double> values);

}  // namespace arucotag::internal

// Reprojection helpers shared by the single-marker and the bundle PnP (internal to arucotag_core).
#pragma once

#include <vector>

#include <opencv2/core.hpp>

#include <arucotag/aruco_tag.hpp>
#include <arucotag/pose.hpp>

namespace arucotag::internal {

/// The cross-product matrix of v: Skew(v) * w = v x w.
cv::Matx33d Skew(const cv::Vec3d& v);

/// Angle (rad) of the rotation between two Rodrigues rotations.
double RotationAngle(const cv::Vec3d& a, const cv::Vec3d& b);

/// Projects `object` (points in the frame that (rvec, tvec) carries into the optical frame) through
/// the camera's lens and pixel mapping into this image's pixels, and fills `jacobian` (2N x 6,
/// CV_64F, rows x then y of each point) with the derivative of each projection by (tvec, small
/// rotation about the camera axes applied on the left), the parametrization of PoseCovariance.
/// Returns false when a point is not in front of the camera or a value is not finite.
bool ProjectWithJacobian(const CameraModel& camera, const std::vector<cv::Point3d>& object, const cv::Vec3d& rvec,
                         const cv::Vec3d& tvec, std::vector<cv::Point2d>& projected, cv::Mat& jacobian);

/// The corner noise (image px per coordinate) the renders calibrated for a marker of mean side
/// `side_px` (image px) whose corners the whole-pattern fit placed (`pattern_fitted`) or the edge fit
/// alone.
double CornerSigmaPrior(double side_px, bool pattern_fitted);

/// Corner noise (image px per coordinate) from a least-squares residual `sum_sq` with
/// `residual_dof` degrees of freedom, pooled with a prior: `prior_sigma` (CornerSigmaPrior) and the
/// camera's own `camera_noise` (px, CameraModel::corner_noise), added in quadrature.
double PooledCornerSigma(double sum_sq, double residual_dof, double prior_sigma, double camera_noise);

/// sigma^2 (J^T J)^-1 from the normal matrix J^T J; unknown when it is singular.
PoseCovariance CovarianceFromNormalMatrix(const cv::Matx66d& jtj, double sigma);

/// How likely the rival planar solution is against the pick (its posterior weight in [0, 0.5] when
/// the pick fits better), from the two least-squares residuals `pick_sum_sq` and `rival_sum_sq`
/// (image px^2) under the corner noise `corner_sigma` (px) that the covariances assume.
double RivalWeight(double pick_sum_sq, double rival_sum_sq, double corner_sigma);

/// One planar solution with its covariance (see PoseCovariance).
struct PoseEstimate {
  cv::Vec3d rvec, tvec;
  PoseCovariance covariance;
};

/// The covariance about `pick` of the mixture of `pick` and `rival` weighed 1 - weight : weight,
/// each with its own covariance: what the pick's own neighbourhood misses when the corners cannot
/// rule out the other planar solution. `pick.covariance` itself when the weight is negligible or a
/// pose is not finite; the pick's own covariance stands in for an unknown rival's.
PoseCovariance CovarianceWithRival(const PoseEstimate& pick, const PoseEstimate& rival, double weight);

}  // namespace arucotag::internal

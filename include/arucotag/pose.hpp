#pragma once

#include <array>
#include <limits>
#include <vector>

#include <opencv2/core.hpp>
#include <pcl/point_cloud.h>
#include <pcl/point_types.h>

#include <arucotag/aruco_tag.hpp>

namespace arucotag {

/// The lens model a CameraModel's distortion coefficients belong to.
enum class DistortionModel {
  kRadialTangential,  ///< OpenCV's pinhole model (ROS plumb_bob, rational_polynomial)
  kEquidistant,       ///< OpenCV's cv::fisheye model (ROS equidistant): r = f * theta_d, k1..k4
};

/// Where an image's pixels lie in the pixel grid the camera was calibrated in. Sensor binning and a
/// region of interest shrink and crop the image but leave K and D describing the full sensor; this
/// affine map carries image pixels to full-sensor pixels, pixel centres at integer coordinates in
/// both (OpenCV's convention).
struct PixelMapping {
  cv::Vec2d scale{1.0, 1.0};   ///< full-sensor pixels per image pixel, x and y
  cv::Vec2d offset{0.0, 0.0};  ///< full-sensor position of image pixel (0, 0)

  /// Binning (b >= 1 sensor pixels summed into one image pixel along each axis) after a crop whose
  /// top-left corner is full-sensor pixel `roi_offset`: image pixel u covers sensor pixels
  /// roi + u*b .. roi + u*b + b-1, so its centre is (u + 0.5) * b - 0.5 + roi. (image_geometry's
  /// toFullResolution uses u * b + roi, which drops the (b - 1) / 2 centring term: a quarter of an
  /// image pixel at 2x binning.) Throws arucotag::Error when a binning is below 1.
  static PixelMapping FromBinningAndRoi(int binning_x, int binning_y, const cv::Point2d& roi_offset);

  cv::Point2d ToSensor(const cv::Point2d& image) const;   ///< image pixel -> full-sensor pixel
  cv::Point2d ToImage(const cv::Point2d& sensor) const;   ///< full-sensor pixel -> image pixel
  bool IsIdentity() const;
};

/// Intrinsics of the camera that took the frame.
struct CameraModel {
  cv::Matx33d K = cv::Matx33d::zeros();  ///< fx 0 cx; 0 fy cy; 0 0 1, full-sensor pixels
  /// Distortion coefficients. kRadialTangential: OpenCV order (k1 k2 p1 p2 [k3 [k4 k5 k6 [s1..s4
  /// [tx ty]]]]), 0, 4, 5, 8, 12 or 14 values, empty for a rectified image. kEquidistant: exactly
  /// k1 k2 k3 k4 (all zero is still a fisheye lens, r = f * theta).
  std::vector<double> distortion;
  DistortionModel distortion_model = DistortionModel::kRadialTangential;
  /// Image pixels -> the pixels K and distortion were calibrated in (identity without binning/ROI).
  PixelMapping pixels;
  /// px (image pixels, per coordinate): corner error a real camera adds to what the pose
  /// covariances were calibrated for, and which four corners' residual cannot show: the
  /// calibration's lens-model residual, compression, motion blur. Added in quadrature to the corner
  /// noise measured on still, lossless renders through their exact intrinsics (0.006-0.009 px for
  /// 20-40 px markers). The default was measured on the sample recording (moving camera, motion
  /// blur up to 2.6 px, sensor noise, JPEG quality 80, exact intrinsics): 0.03-0.07 px per marker.
  /// Set it to your calibration's reprojection RMS when that is larger; 0 for a still, lossless
  /// render through the very intrinsics.
  double corner_noise = kDefaultCornerNoise;
  static constexpr double kDefaultCornerNoise = 0.05;

  /// From K and distortion (a raw image through a pinhole lens).
  static CameraModel FromIntrinsics(const cv::Matx33d& K, const std::vector<double>& distortion);
  /// From K and the four equidistant coefficients k1..k4 (a raw image through a fisheye lens).
  static CameraModel FromFisheye(const cv::Matx33d& K, const std::vector<double>& distortion);
  /// From the 3x4 projection matrix P of a rectified image: its left 3x3 block, no distortion.
  static CameraModel FromProjection(const cv::Matx34d& P);

  /// Throws arucotag::Error when fx or fy is not a positive finite number, another entry of K is
  /// not finite, K's last row is not 0 0 1, the distortion count is not one the model accepts, a
  /// coefficient is not finite, the pixel mapping's scale is not positive and finite, or
  /// corner_noise is negative or not finite.
  void Validate() const;

  /// Image pixels (this image, after binning/ROI) of points given in the marker frame, seen with
  /// the marker -> camera rotation (Rodrigues) and translation. Points must be in front of the lens.
  std::vector<cv::Point2d> Project(const std::vector<cv::Point3d>& points, const cv::Vec3d& rvec,
                                   const cv::Vec3d& tvec) const;
  /// Normalized image coordinates (x/z, y/z of the ray) of image pixels: the pixel mapping undone,
  /// then the lens distortion. A fisheye pixel more than 90 degrees off axis has no such coordinate.
  std::vector<cv::Point2d> Normalize(const std::vector<cv::Point2d>& image) const;
};

/// Solves the marker's pose from its four corners with cv::solvePnPGeneric(SOLVEPNP_IPPE_SQUARE)
/// on object points centred on the marker (TL, TR, BR, BL, side tag.side_length), honouring the
/// camera's pixel mapping and lens model (the corners are normalized first, so pinhole and fisheye
/// lenses share one solver). Keeps both IPPE solutions in tag.pnp with their RMS reprojection
/// errors (image pixels), the ambiguity ratio (best / second RMS) and a covariance each (see
/// PnpResult). When IPPE stopped off its minimum (one Gauss-Newton step would remove over half its
/// squared error: OpenCV's IPPE degenerates on some exactly frontal views) each solution is refined
/// within its own basin and a global solver (SQPNP from OpenCV 4.5.3, ITERATIVE before) may replace
/// the one nearest to it, so the pair stays two distinct solutions. Then sets the tag's pose (see
/// ResolvePose: fused when the tag already has a cloud result). Returns false (pose untouched) when
/// OpenCV finds no solution. Throws arucotag::Error on invalid intrinsics or a non-positive side
/// length.
bool EstimatePoseFromPNP(const CameraModel& camera, ArucoTag& tag);

/// How EstimatePoseFromPointCloud fits the marker plane to the tag's points.
enum class PlaneFit {
  /// PCL's RANSAC (pcl::RandomSampleConsensus, pcl::SampleConsensusModelPlane) with an inlier
  /// threshold of three times the depth noise at the tag's range, then least squares on the
  /// inliers: rejects background seen past the tag's edge however many points it has, up to half.
  kRansac,
  kMsac,   ///< the same with PCL's MSAC (pcl::MEstimatorSampleConsensus)
  kLmeds,  ///< the same with PCL's least median of squares (pcl::LeastMedianSquares)
  kMlesac,  ///< the same with PCL's MLESAC (pcl::MaximumLikelihoodSampleConsensus)
  /// Least squares, then points beyond three robust sigmas (MAD) of the residuals dropped, three
  /// rounds (arucotag before PCL): a large share of background points drags the first fit, and
  /// the rejection with it. Kept for comparison (bench_pose).
  kLegacy,
};

/// Tuning of EstimatePoseFromPointCloud.
struct CloudPoseOptions {
  double shrink = 0.15;   ///< fraction of the half-side trimmed from each edge (stereo edges bleed)
  int min_points = 12;    ///< fewer finite points than this -> failure
  int min_plane_points = 30;  ///< fewer -> centre only, no normal/rotation
  int max_samples = 4000;  ///< subsample large tags to this many points (speed, not accuracy)
  /// The depth camera's noise model sigma_z = depth_noise_per_m2 * z^2 (1/m); for a stereo camera
  /// sigma_d / (f * B): disparity noise (px) over focal length (px) times baseline (m). Default: a
  /// ZED 2 at HD720 (0.15 px / (700 px * 0.12 m)). Stereo noise is correlated and hides in small
  /// plane residuals, so this is the floor of the plane's depth noise.
  double depth_noise_per_m2 = 0.0018;
  PlaneFit plane_fit = PlaneFit::kRansac;  ///< see PlaneFit
};

/// Measures the tag from an organized cloud (CV_32FC3, one XYZ point per image pixel, in the image's
/// optical frame, metres, NaN where there is no depth). Uses the finite points inside the tag's
/// quadrilateral shrunk by options.shrink, fits the marker plane robustly (options.plane_fit:
/// background and flying pixels rejected), takes the centre where the fit puts the marker centre, the face normal and,
/// with enough points, the in-plane orientation, and the covariance of centre and rotation from the
/// fit's residuals and point count, widened for correlated stereo noise by the camera's depth-noise
/// model (options.depth_noise_per_m2). Fills tag.cloud and then the tag's pose (see
/// ResolvePose). Returns false with tag.cloud.valid false when fewer than options.min_points finite
/// points exist (the pose falls back to PnP if the tag has one, else none): it never produces a
/// number made of NaNs. Throws arucotag::Error when the cloud is
/// not CV_32FC3 or its size differs from image_size.
bool EstimatePoseFromPointCloud(const cv::Mat& cloud, const cv::Size& image_size, ArucoTag& tag,
                                const CloudPoseOptions& options = {});

/// The same from an organized PCL cloud (one point per image pixel: width x height is the image's
/// size), for example one pcl::fromROSMsg made of a sensor_msgs/PointCloud2. Throws arucotag::Error
/// when the cloud is not organized (height 1) or holds other than width x height points.
bool EstimatePoseFromPointCloud(const pcl::PointCloud<pcl::PointXYZ>& cloud, ArucoTag& tag,
                                const CloudPoseOptions& options = {});

/// What FusedChoice weighs, for a tag with two PnP solutions and a cloud plane (usable false
/// otherwise): chi-square differences between solution 1 and solution 0 (positive: the evidence
/// favours solution 0, the corners' pick, for `corners`; solution 1 for `cloud`), and the angles
/// (rad) between the cloud's normal and each solution's, with the normal's standard deviation.
struct FusedEvidence {
  bool usable = false;
  double corners = 0.0;
  double cloud = 0.0;
  std::array<double, 2> angle{{0.0, 0.0}};
  double normal_sigma = std::numeric_limits<double>::quiet_NaN();
};
FusedEvidence WeighFusedEvidence(const ArucoTag& tag);

/// Which of the tag's two PnP solutions (0 = the corners' pick) the fused pose takes. Each
/// measurement weighs in with a chi-square difference between the solutions under its own noise:
/// the corners' from the two reprojection errors (corner noise estimated from the better one's
/// residuals, at least 0.1 px), the cloud's from the angles between its plane normal and each
/// solution's, over the normal's standard deviation (plane residuals and point count, capped for
/// correlated stereo noise, plus 5 degrees of systematic error in quadrature). The cloud overrides the corners only when its evidence exceeds theirs
/// by 9 (three sigma), the normals differ by 2 degrees or more, the plane lies within 15 degrees
/// of the solution it favours or twice the normal's standard deviation if that is more (further, it
/// is not this face). 0 without a plane or a second solution.
int FusedChoice(const ArucoTag& tag);

/// Sets the tag's pose (rvec, tvec, distance, yaw, pose_source, reprojection_error,
/// depth_disagreement, covariance, orientation_measured) from tag.pnp and tag.cloud, preferring
/// `wanted`:
/// - kPnp: the PnP solution with the lower reprojection error. Its covariance is the second moment,
///   about it, of both planar solutions weighed by their likelihoods under twice the corner noise
///   (each with its own first-order covariance): where the corners cannot rule out the other
///   solution (small, near-frontal markers) the covariance spans it, elsewhere the rival's weight is
///   negligible and it is the pick's own.
/// - kPointCloud: the cloud's centre and orientation with the cloud's covariance (PnP's rotation
///   and rotation covariance, as kPnp's, fill in when the cloud could not recover one; with neither,
///   the orientation is a guess facing the camera and orientation_measured is false).
/// - kFused: the IPPE solution FusedChoice picks (no flipped poses), with depth_disagreement between
///   PnP and cloud ranges, then updated by the cloud's centre as a Kalman measurement weighed by the
///   two covariances (PnP's centre-rotation correlation carries it into the rotation too); a centre
///   more than the chi-square 99.9 % gate away (another surface, a stale cloud) is left out and the
///   pose and covariance are that PnP solution's. A cloud without a plane leaves the flip to the
///   corners: the covariance starts from kPnp's.
/// Falls back to whatever is available when `wanted` is not; kNone clears the pose. Returns the
/// source actually used.
PoseSource ResolvePose(ArucoTag& tag, PoseSource wanted);

}  // namespace arucotag

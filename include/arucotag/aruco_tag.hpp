#pragma once

#include <array>
#include <limits>
#include <stdexcept>
#include <string>

#include <opencv2/core.hpp>

namespace arucotag {

/// Every error the core reports: bad input, bad configuration. The core never logs and never exits.
class Error : public std::runtime_error {
 public:
  using std::runtime_error::runtime_error;
};

/// Which measurement produced a tag's final pose.
enum class PoseSource {
  kNone = 0,        ///< no pose: ids and corners only
  kPnp = 1,         ///< perspective-n-point on the four corners
  kPointCloud = 2,  ///< organized point cloud only
  kFused = 3,       ///< PnP solution chosen by the point cloud's plane, updated by its centre
};

/// Lower-case name of a pose source ("none", "pnp", "point_cloud", "fused").
const char* PoseSourceName(PoseSource source);

/// Covariance of a pose, row-major, in the order of geometry_msgs/PoseWithCovariance: x, y, z of
/// the position (m), then small rotations about the x, y, z axes of the frame the pose is expressed
/// in (rad, applied on the left: R_true = exp([dtheta]x) R_estimate). All NaN when there is no pose.
using PoseCovariance = cv::Matx<double, 6, 6>;

/// A covariance with every entry NaN: what an unmeasured pose carries.
inline PoseCovariance UnknownCovariance() { return PoseCovariance::all(std::numeric_limits<double>::quiet_NaN()); }

/// Both solutions of the planar PnP problem (IPPE always yields two for a square).
struct PnpResult {
  bool valid = false;
  std::array<cv::Vec3d, 2> rvec{};  ///< marker -> camera rotation (Rodrigues), best first
  std::array<cv::Vec3d, 2> tvec{};  ///< marker centre in the camera optical frame (m), best first
  std::array<double, 2> rms{{std::numeric_limits<double>::quiet_NaN(),
                             std::numeric_limits<double>::quiet_NaN()}};  ///< RMS reprojection error (px)
  int solutions = 0;  ///< how many of the two slots are filled
  /// rms[0] / rms[1] in [0, 1]: near 0 the best solution is clearly right, near 1 the two are
  /// indistinguishable from the corners alone (a possible pose flip). The two slots are always the
  /// two planar (IPPE) solutions, locally refined when IPPE was off its minimum, so a solver
  /// fallback never pairs a solution with a copy of itself. NaN with a single solution.
  double ambiguity = std::numeric_limits<double>::quiet_NaN();
  /// Covariance of each solution (optical frame): corner_sigma^2 (J^T J)^-1 with J the reprojection
  /// Jacobian at that solution. First-order: it describes the neighbourhood of its own solution and
  /// says nothing about the flip, which `ambiguity` reports (the tag's covariance under PnP adds the
  /// other solution by its likelihood: see ResolvePose).
  std::array<PoseCovariance, 2> covariance{{UnknownCovariance(), UnknownCovariance()}};
  /// Corner noise the covariances assume (image px, per coordinate): the residual of the best
  /// solution (2 degrees of freedom) pooled with the corner refinement's accuracy as a prior.
  double corner_sigma = std::numeric_limits<double>::quiet_NaN();
};

/// What the organized point cloud says about a tag.
struct CloudResult {
  bool valid = false;
  int points = 0;          ///< finite points used (inliers of the robust fit)
  cv::Vec3d centre{};      ///< robust estimate of the tag centre, optical frame (m)
  bool has_normal = false;  ///< a plane could be fitted
  cv::Vec3d normal{};       ///< unit normal of the tag face, pointing towards the camera
  bool has_rotation = false;  ///< in-plane orientation recovered too
  cv::Matx33d rotation = cv::Matx33d::eye();  ///< marker -> camera rotation from the cloud
  double plane_rms = std::numeric_limits<double>::quiet_NaN();  ///< RMS distance of inliers to the plane (m)
  /// Standard deviation of `normal` (rad): the plane residuals or the camera's depth noise at that
  /// range (CloudPoseOptions::depth_noise_per_m2), whichever is larger, over the points' lever arm,
  /// plus a systematic 5 degrees. What FusedChoice weighs the cloud's evidence by.
  double normal_sigma = std::numeric_limits<double>::quiet_NaN();
  /// Covariance of (centre, rotation) in the optical frame, from the fit's residuals and point
  /// count, widened for correlated stereo noise (CloudPoseOptions::depth_noise_per_m2). Without a
  /// rotation the rotation block is unknown (pi^2 on its diagonal, no correlation).
  PoseCovariance covariance = UnknownCovariance();
};

/// One detected marker. Pixel coordinates have their origin at the top-left pixel's centre (OpenCV).
/// Poses are in the camera optical frame: x right, y down, z forward. The marker frame follows
/// cv::aruco: origin at the marker centre, x to the marker's right, y up, z out of the printed face.
struct ArucoTag {
  int id = -1;
  /// Corners as cv::aruco returns them: top-left, top-right, bottom-right, bottom-left in the
  /// marker's own frame (so rotated markers have rotated corner lists), px.
  std::array<cv::Point2f, 4> corners{};
  /// True when Detect's whole-pattern fit placed the corners (DetectorConfig::pattern_fit_max_side),
  /// about twice as accurate as the edge fit alone: EstimatePoseFromPNP assumes the corner noise of
  /// the refinement that placed them.
  bool pattern_fitted = false;
  double side_length = 0.15;  ///< side of the black square used for the pose (m)

  PoseSource pose_source = PoseSource::kNone;  ///< which measurement the pose below comes from
  cv::Vec3d rvec{};  ///< marker -> camera rotation (Rodrigues vector)
  cv::Vec3d tvec{};  ///< marker centre in the camera optical frame (m)
  double distance = std::numeric_limits<double>::quiet_NaN();  ///< |tvec| (m)
  double yaw = std::numeric_limits<double>::quiet_NaN();  ///< atan2(x, z) (rad), positive = tag right of the axis
  double reprojection_error = std::numeric_limits<double>::quiet_NaN();  ///< RMS of the chosen PnP solution (px)
  /// |PnP range - cloud range| (m) when both are known: how far the two measurements agree.
  double depth_disagreement = std::numeric_limits<double>::quiet_NaN();
  /// Covariance of (tvec, rotation) in the optical frame (see PoseCovariance); NaN without a pose.
  PoseCovariance covariance = UnknownCovariance();
  /// False when nothing measured the orientation (a cloud too sparse for a plane and no PnP): rvec
  /// is then only a guess (facing the camera, upright) and the rotation variances are pi^2.
  bool orientation_measured = false;

  PnpResult pnp;      ///< filled by EstimatePoseFromPNP
  CloudResult cloud;  ///< filled by EstimatePoseFromPointCloud

  bool HasPose() const { return pose_source != PoseSource::kNone; }
};

/// Projected centre of the tag: the intersection of the quadrilateral's diagonals, which is where
/// the square's true centre lands under perspective (the corner mean is not). Falls back to the
/// corner mean when the diagonals are parallel or cross outside the quadrilateral (degenerate quad).
cv::Point2f FindTagCenter(const ArucoTag& tag);

}  // namespace arucotag

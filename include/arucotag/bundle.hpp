#pragma once

#include <array>
#include <limits>
#include <string>
#include <vector>

#include <opencv2/core.hpp>

#include <arucotag/aruco_tag.hpp>
#include <arucotag/pose.hpp>

namespace arucotag {

/// One marker of a bundle: where it sits on the rigid object.
struct BundleMember {
  int id = -1;
  double side_length = 0.0;  ///< m, black square side
  /// Marker frame (cv::aruco: x right, y up, z out of the printed face) -> bundle frame rotation.
  cv::Matx33d rotation = cv::Matx33d::eye();
  cv::Vec3d position{};  ///< m, marker centre in the bundle frame

  /// The four corners TL, TR, BR, BL (cv::aruco's order) in the bundle frame (m).
  std::array<cv::Point3d, 4> Corners() const;
};

/// Several markers on one rigid object (a URC post with a marker on each face), estimated as one
/// pose. A bundle may carry one id on several members (URC posts print the same marker on every
/// face): each detection is then matched to the face its position fits.
struct MarkerBundle {
  std::string name;   ///< unique among the bundles, for messages and errors
  std::string frame;  ///< TF child frame name of the bundle (the nodelet puts it under the camera frame)
  std::vector<BundleMember> members;

  /// Whether a member carries this id.
  bool Contains(int id) const;
};

/// Rotation of fixed-axis roll, pitch, yaw (rad, URDF and tf2 order): R = Rz(yaw) Ry(pitch) Rx(roll).
cv::Matx33d RotationFromRpy(double roll, double pitch, double yaw);

/// Throws arucotag::Error naming the bundle (and the member id) on: an empty name or frame, two
/// bundles with one name, a bundle without members, a negative id, a side length that is not a
/// positive finite number, a non-finite position, a rotation that is not a proper rotation matrix,
/// an id in two bundles (a detection could not tell which object it belongs to), or one id twice in
/// a bundle at the same place (a copied line: 1 mm apart or less).
void ValidateBundles(const std::vector<MarkerBundle>& bundles);

/// Parses and validates (ValidateBundles) the bundle list `node` of an OpenCV FileStorage (yaml or
/// json): a sequence of maps with `name`, `frame` (default: the name) and `members`, a sequence of
/// maps with `id`, `size` (m), `position` ([x, y, z] m, default 0 0 0) and `rpy_deg` ([roll, pitch,
/// yaw] deg, fixed axes as RotationFromRpy, default 0 0 0), as config/urc_bundles.yaml. An absent
/// or empty node is no bundles. Throws arucotag::Error naming the bundle and member on a missing
/// key or a wrong type.
std::vector<MarkerBundle> ParseBundles(const cv::FileNode& node);

/// ParseBundles on the `bundles` key of a yaml or json text (as rosparam loads it: a yaml text
/// needs no %YAML directive). Throws arucotag::Error when the text does not parse.
std::vector<MarkerBundle> BundlesFromText(const std::string& text);

/// BundlesFromText on the contents of a file. Throws arucotag::Error when it cannot be read.
std::vector<MarkerBundle> LoadBundles(const std::string& path);

/// One bundle's pose in one image.
struct BundlePose {
  bool valid = false;
  std::string name;  ///< the bundle's
  PoseSource pose_source = PoseSource::kNone;  ///< kPnp, or kFused when a cloud picked the solution
  cv::Vec3d rvec{};  ///< bundle -> camera rotation (Rodrigues)
  cv::Vec3d tvec{};  ///< bundle origin in the camera optical frame (m)
  /// Covariance of (tvec, rotation) in the optical frame (see PoseCovariance): corner_sigma^2
  /// (J^T J)^-1 with J the reprojection Jacobian of every corner used; with one face seen and no
  /// cloud, widened by that face's other planar solution as a tag's is (see ResolvePose, kPnp).
  PoseCovariance covariance = UnknownCovariance();
  /// Ids of the members whose corners were used, one entry per member (an id shared by several
  /// faces appears once per face seen), in the bundle's member order.
  std::vector<int> member_ids;
  std::vector<int> members;  ///< indices into MarkerBundle::members of the same members
  std::vector<int> tags;     ///< indices into the tags given of the detections used, same order
  double reprojection_error = std::numeric_limits<double>::quiet_NaN();  ///< px, RMS per coordinate
  double corner_sigma = std::numeric_limits<double>::quiet_NaN();  ///< px, corner noise the covariance assumes
};

/// Estimates the bundle's pose in the optical frame from every visible member jointly: each
/// detection whose id the bundle carries is matched to a member (by where the hypotheses below put
/// the members; a face turned away from the camera matches nothing), and one Levenberg-Marquardt
/// PnP (cv::solvePnPRefineLM, on normalized points as EstimatePoseFromPNP) runs over all 4k
/// corners. The start is the best of the hypotheses "detection d is member m" from both IPPE
/// solutions of each detection with the member's side length (a pair a joint hypothesis already
/// matched seeds none): the one that matches most members, then the lowest error. With one member seen and a cloud result on its detection
/// (EstimatePoseFromPointCloud ran on the tag), the cloud picks between its two solutions as
/// FusedChoice does for a tag; two faces at an angle fix the pose without it. Returns a pose with
/// valid false when no member is seen or no solution is in front of the camera. Throws
/// arucotag::Error on invalid intrinsics.
BundlePose EstimateBundlePose(const CameraModel& camera, const MarkerBundle& bundle, const std::vector<ArucoTag>& tags);

}  // namespace arucotag

#pragma once

#include <vector>

#include <opencv2/core.hpp>

#include <arucotag/aruco_tag.hpp>

namespace arucotag {

/// Intrinsics of the camera that took the frame.
struct CameraModel {
  cv::Matx33d K = cv::Matx33d::zeros();  ///< fx 0 cx; 0 fy cy; 0 0 1
  /// Distortion coefficients in OpenCV order (k1 k2 p1 p2 [k3 [k4 k5 k6 [s1..s4 [tx ty]]]]): 0, 4, 5,
  /// 8, 12 or 14 values. Empty for a rectified image.
  std::vector<double> distortion;

  /// From K and distortion (a raw image).
  static CameraModel FromIntrinsics(const cv::Matx33d& K, const std::vector<double>& distortion);
  /// From the 3x4 projection matrix P of a rectified image: its left 3x3 block, no distortion.
  static CameraModel FromProjection(const cv::Matx34d& P);

  /// Throws arucotag::Error when fx or fy is not a positive finite number, cx/cy are not finite, or
  /// the distortion count is one OpenCV does not accept.
  void Validate() const;
};

/// Solves the marker's pose from its four corners with cv::solvePnPGeneric(SOLVEPNP_IPPE_SQUARE)
/// on object points centred on the marker (TL, TR, BR, BL, side tag.side_length), honouring the
/// camera's distortion. Keeps both IPPE solutions in tag.pnp with their RMS reprojection errors and
/// the ambiguity ratio, then sets the tag's pose (see ResolvePose: fused when the tag already has a
/// cloud result). Returns false (pose untouched) when OpenCV finds no solution. Throws
/// arucotag::Error on invalid intrinsics or a non-positive side length.
bool EstimatePoseFromPNP(const CameraModel& camera, ArucoTag& tag);

/// Tuning of EstimatePoseFromPointCloud.
struct CloudPoseOptions {
  double shrink = 0.15;   ///< fraction of the half-side trimmed from each edge (stereo edges bleed)
  int min_points = 12;    ///< fewer finite points than this -> failure
  int min_plane_points = 30;  ///< fewer -> centre only, no normal/rotation
  int max_samples = 4000;  ///< subsample large tags to this many points (speed, not accuracy)
};

/// Measures the tag from an organized cloud (CV_32FC3, one XYZ point per image pixel, in the image's
/// optical frame, metres, NaN where there is no depth). Uses the finite points inside the tag's
/// quadrilateral shrunk by options.shrink, fits the marker plane robustly (outliers rejected by
/// their residual), takes the centre where the fit puts the marker centre, the face normal and,
/// with enough points, the in-plane orientation. Fills tag.cloud and then the tag's pose (see
/// ResolvePose). Returns false with tag.cloud.valid false when fewer than options.min_points finite
/// points exist (the pose falls back to PnP if the tag has one, else none): it never produces a
/// number made of NaNs. Throws arucotag::Error when the cloud is
/// not CV_32FC3 or its size differs from image_size.
bool EstimatePoseFromPointCloud(const cv::Mat& cloud, const cv::Size& image_size, ArucoTag& tag,
                                const CloudPoseOptions& options = {});

/// Sets the tag's pose (rvec, tvec, distance, yaw, pose_source, reprojection_error,
/// depth_disagreement) from tag.pnp and tag.cloud, preferring `wanted`:
/// - kPnp: the PnP solution with the lower reprojection error.
/// - kPointCloud: the cloud's centre and orientation (PnP's rotation fills in when the cloud could
///   not recover one).
/// - kFused: the IPPE solution whose face normal agrees with the cloud's plane (no flipped poses),
///   with depth_disagreement between PnP and cloud ranges.
/// Falls back to whatever is available when `wanted` is not; kNone clears the pose. Returns the
/// source actually used.
PoseSource ResolvePose(ArucoTag& tag, PoseSource wanted);

}  // namespace arucotag

#pragma once

// The detector nodelet's private parameters: reading, validating, and the dynamic_reconfigure view.
#include <string>
#include <vector>

#include <ros/node_handle.h>

#include <arucotag/ArucotagDetectorConfig.h>
#include <arucotag/aruco_tag.hpp>
#include <arucotag/bundle.hpp>
#include <arucotag/detector.hpp>
#include <arucotag/pose.hpp>
#include <arucotag/preprocess.hpp>
#include <arucotag/tracker.hpp>

namespace arucotag {

/// Everything the nodelet reads from its private namespace (config/detector.yaml documents each).
struct NodeletParameters {
  DetectorConfig detector;        ///< dictionary, tag_size(s), id lists, cv::aruco parameters
  PreprocessOptions preprocess;   ///< equalize, clahe_*, unsharp_*
  /// ~image_transport: which of <image> and <image>/compressed to read; auto takes both until the
  /// first message arrives and keeps the transport it came on.
  enum class Transport { kAuto, kRaw, kCompressed } transport = Transport::kAuto;
  bool use_point_cloud = false;
  int queue_size = 10;
  PoseSource pose_source = PoseSource::kFused;
  CloudPoseOptions cloud;          ///< ~depth_noise sets cloud.depth_noise_per_m2
  bool publish_tf = true;
  std::string output_frame;        ///< empty: poses stay in the image's frame
  /// TF child frame = frame_prefix + id; empty (the default): "<image frame_id>/aruco_", so two
  /// cameras never publish the same child frame.
  std::string frame_prefix;
  bool rectified = false;          ///< camera model from P (rectified image) instead of K + D
  /// px, CameraModel::corner_noise of the camera models made from camera_info: the corner error the
  /// camera adds (calibration residual, compression, motion blur) to what the pose covariances assume
  double corner_noise = CameraModel::kDefaultCornerNoise;
  double camera_info_max_age = 0.0;  ///< s between image and camera_info stamps before a warning; 0: any age
  double camera_info_wait = 1.0;     ///< s images wait for the first camera_info (only before one has come)
  double cloud_max_dt = 0.1;         ///< s, largest stamp difference of an image and the cloud it is paired with
  int cloud_cache_size = 4;          ///< clouds kept for pairing (they are large)
  /// ~track_*: validation, dropping, gate, process noise, association. `filter` follows output_frame:
  /// only a frame that does not move with the camera gives poses worth filtering.
  TrackerConfig tracker;
  bool tf_from_validated_tracks = false;  ///< TF from validated tracks' filtered poses, not from detections
  std::vector<MarkerBundle> bundles;  ///< ~bundles (config/urc_bundles.yaml), validated; empty: none
};

/// The track fuser's private parameters (arucotag/TrackFuser; README, "Fusing cameras").
struct FuserParameters {
  std::vector<std::string> inputs;  ///< ~inputs: ArucoTagArray topics of detectors with ~output_frame; at least one
  std::string fixed_frame;          ///< ~output_frame: the frame every input's poses must be in; required
  int queue_size = 10;
  TrackerConfig tracker;            ///< ~track_*, as the detector reads them; `filter` always on
  bool publish_tf = true;           ///< TF <frame_prefix><id> from validated tracks
  std::string frame_prefix = "fused/aruco_";  ///< ~frame_prefix; "" also means this default
};

/// Reads and validates the track fuser's private parameters; throws arucotag::Error naming the
/// offending one, as ReadParameters.
FuserParameters ReadFuserParameters(const ros::NodeHandle& pnh);

/// Private parameters present on the server that ReadFuserParameters does not read.
std::vector<std::string> UnknownFuserParameters(const ros::NodeHandle& pnh);

/// Reads and validates the private parameters. Throws arucotag::Error naming the offending
/// parameter ("~tag_size must be > 0 m, got -1") on a wrong type or value; absent ones keep their
/// defaults.
NodeletParameters ReadParameters(const ros::NodeHandle& pnh);

/// Private parameters present on the server that ReadParameters does not read (likely typos).
std::vector<std::string> UnknownParameters(const ros::NodeHandle& pnh);

/// Copies the live-tunable detector and preprocessing values out of a dynamic_reconfigure config.
void ApplyReconfigure(const ArucotagDetectorConfig& config, DetectorConfig& detector, PreprocessOptions& preprocess);

/// The dynamic_reconfigure view of the values in use.
ArucotagDetectorConfig ToReconfigure(DetectorConfig detector, PreprocessOptions preprocess);

/// Copies the live-tunable track values (~track_*, ~tf_from_validated_tracks) out of a config; the
/// tracker's `filter` stays. Throws arucotag::Error when they are not a valid TrackerConfig.
void ApplyTrackReconfigure(const ArucotagDetectorConfig& config, TrackerConfig& tracker, bool& tf_from_validated_tracks);

/// Sets the track values of a dynamic_reconfigure config to the ones in use.
void TrackToReconfigure(const TrackerConfig& tracker, bool tf_from_validated_tracks, ArucotagDetectorConfig& config);

}  // namespace arucotag

#pragma once

// The detector nodelet's private parameters: reading, validating, and the dynamic_reconfigure view.
#include <string>
#include <vector>

#include <ros/node_handle.h>

#include <arucotag/ArucotagDetectorConfig.h>
#include <arucotag/aruco_tag.hpp>
#include <arucotag/detector.hpp>
#include <arucotag/preprocess.hpp>

namespace arucotag {

/// Everything the nodelet reads from its private namespace (config/detector.yaml documents each).
struct NodeletParameters {
  DetectorConfig detector;        ///< dictionary, tag_size(s), id lists, cv::aruco parameters
  PreprocessOptions preprocess;   ///< equalize, clahe_*, unsharp_*
  bool compressed = false;        ///< ~image_transport: compressed (else raw)
  bool use_point_cloud = false;
  bool approximate_sync = true;
  int queue_size = 10;
  PoseSource pose_source = PoseSource::kFused;
  bool publish_tf = true;
  std::string output_frame;        ///< empty: poses stay in the image's frame
  std::string frame_prefix = "aruco_";
  bool rectified = false;          ///< camera model from P (rectified image) instead of K + D
  double input_timeout = 1.0;      ///< s of image stamps without a synchronized set before images are used alone
  double tf_timeout = 0.05;        ///< s to wait for a transform at the image stamp
};

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

}  // namespace arucotag

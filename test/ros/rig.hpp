#pragma once

// Test rig for the rostests: renders scenes with arucotag::sim, publishes them as the camera driver
// would (image, camera_info, organized cloud, compressed image) and collects what the detector
// publishes, keyed by the image stamp. ROS-free truth (sim) against the real nodelet's output.
#include <map>
#include <mutex>
#include <optional>
#include <string>
#include <vector>

#include <arucotag/ArucoTagArray.h>
#include <geometry_msgs/TransformStamped.h>
#include <gtest/gtest.h>
#include <geometry_msgs/Pose.h>
#include <geometry_msgs/Transform.h>
#include <opencv2/core.hpp>
#include <ros/ros.h>
#include <sensor_msgs/CameraInfo.h>
#include <sensor_msgs/CompressedImage.h>
#include <sensor_msgs/Image.h>
#include <sensor_msgs/PointCloud2.h>
#include <visualization_msgs/MarkerArray.h>

#include <arucotag/sim.hpp>

namespace arucotag::test {

constexpr const char* kOpticalFrame = "cam_optical";
constexpr const char* kBodyFrame = "cam_body";  // x forward, y left, z up, as stereo drivers publish clouds

/// The fixed transform body <- optical the rig publishes as a static TF (rotation + translation).
cv::Matx33d BodyFromOpticalRotation();
cv::Vec3d BodyFromOpticalTranslation();
geometry_msgs::TransformStamped BodyFromOpticalTf();

/// A rendered frame and its truth.
struct Scene {
  sim::Camera camera;
  std::vector<sim::Marker> markers;
  cv::Mat image;  ///< bgr8
  cv::Mat cloud;  ///< CV_32FC3, optical frame
};

/// 640x480, 60 degrees horizontal field of view, no distortion.
sim::Camera TestCamera();
/// The cloud comes from `stereo` (a ZED 2's stereo noise unless told otherwise).
Scene Render(const std::vector<sim::Marker>& markers, const sim::RenderOptions& options = {},
             const sim::DepthNoise& stereo = sim::DepthNoise::Zed2());

/// What a published frame carries; the rig fills the rest from the scene.
struct Channels {
  bool image = true;          ///< sensor_msgs/Image bgr8 on /cam/image
  bool info = true;           ///< /cam/camera_info
  bool cloud = false;         ///< /cam/points, optical frame
  bool body_cloud = false;    ///< /cam/points_body, cam_body frame
  std::string compressed;     ///< ".jpg" or ".png": also /cam/image/compressed
};

/// Messages of one topic by header stamp.
template <class M>
class Collector {
 public:
  Collector(ros::NodeHandle& nh, const std::string& topic)
      : sub_(nh.subscribe<M>(topic, 20, [this](const boost::shared_ptr<const M>& msg) {
          std::lock_guard<std::mutex> lock(mutex_);
          by_stamp_[Stamp(*msg)].push_back(msg);
        })) {}

  /// All messages with this stamp received so far.
  std::vector<boost::shared_ptr<const M>> At(const ros::Time& stamp) const {
    std::lock_guard<std::mutex> lock(mutex_);
    const auto it = by_stamp_.find(stamp);
    return it == by_stamp_.end() ? std::vector<boost::shared_ptr<const M>>{} : it->second;
  }
  boost::shared_ptr<const M> First(const ros::Time& stamp) const {
    const auto all = At(stamp);
    return all.empty() ? nullptr : all.front();
  }
  /// Spins until a message with the stamp arrives, up to `timeout` s.
  boost::shared_ptr<const M> Wait(const ros::Time& stamp, double timeout) const;
  size_t Publishers() const { return sub_.getNumPublishers(); }

 private:
  static ros::Time Stamp(const M& msg);
  mutable std::mutex mutex_;
  std::map<ros::Time, std::vector<boost::shared_ptr<const M>>> by_stamp_;
  ros::Subscriber sub_;
};

/// Publishes frames as a camera driver would, under /cam.
class Rig {
 public:
  explicit Rig(ros::NodeHandle& nh);

  /// Publishes one frame of the scene at a fresh stamp (after the cloud and info, the image last,
  /// as drivers do) and returns the stamp.
  ros::Time Publish(const Scene& scene, const Channels& channels = {});

  /// Publishes frames of the scene (fresh stamps, every `period` s) until `tags` has an answer for
  /// one of them; returns it, or null after `timeout` s.
  template <class M>
  boost::shared_ptr<const M> PublishUntil(const Scene& scene, const Collector<M>& out, const Channels& channels = {},
                                          double timeout = 8.0, double period = 0.2);

  /// Waits until every named topic has a subscriber (the nodelets are up), up to `timeout` s.
  bool WaitForSubscribers(const std::vector<std::string>& topics, double timeout);

  ros::Publisher& image_pub() { return image_pub_; }
  ros::Publisher& info_pub() { return info_pub_; }
  ros::Publisher& cloud_pub() { return cloud_pub_; }

  static sensor_msgs::ImagePtr ImageMessage(const cv::Mat& bgr, const ros::Time& stamp);
  /// The camera's K and lens (its distortion coefficients and model), P = K.
  static sensor_msgs::CameraInfoPtr InfoMessage(const sim::Camera& camera, const ros::Time& stamp);
  /// Organized XYZ + padding cloud (point_step 16, like drivers' XYZRGB), moved by R, t when given.
  static sensor_msgs::PointCloud2Ptr CloudMessage(const cv::Mat& cloud, const ros::Time& stamp, const std::string& frame,
                                                  const cv::Matx33d& rotation = cv::Matx33d::eye(),
                                                  const cv::Vec3d& translation = cv::Vec3d());

 private:
  ros::NodeHandle nh_;
  ros::Publisher image_pub_, info_pub_, cloud_pub_, body_cloud_pub_, compressed_pub_;
  ros::Time last_stamp_;
};

// Truth and comparison.

/// Marker -> camera rotation of a sim marker.
cv::Matx33d Rotation(const sim::Marker& marker);
/// Rotation of a pose's quaternion.
cv::Matx33d Rotation(const geometry_msgs::Quaternion& q);
/// Angle of a @ b^T (deg).
double AngleDeg(const cv::Matx33d& a, const cv::Matx33d& b);
cv::Vec3d Position(const geometry_msgs::Point& p);

/// The foundation's tolerances: position within 0.5 % of the camera-to-tag range (m), orientation
/// within 1 degree. `rotation` and `position` are the truth in the pose's frame.
::testing::AssertionResult PoseMatches(const geometry_msgs::Pose& pose, const cv::Matx33d& rotation,
                                       const cv::Vec3d& position, double range);
/// Same, against a sim marker seen in the optical frame.
::testing::AssertionResult PoseMatches(const geometry_msgs::Pose& pose, const sim::Marker& truth);
/// Every corner within max_px of the projection of the truth.
::testing::AssertionResult CornersMatch(const arucotag::ArucoTag& tag, const sim::Camera& camera,
                                        const sim::Marker& truth, double max_px = 0.5);

/// Polls `done` every 10 ms until it returns true or `timeout` s have passed; returns its last answer.
template <class Predicate>
bool WaitUntil(Predicate done, double timeout) {
  const ros::WallTime end = ros::WallTime::now() + ros::WallDuration(timeout);
  while (!done()) {
    if (!ros::ok() || ros::WallTime::now() >= end) return done();
    ros::WallDuration(0.01).sleep();
  }
  return true;
}

/// The URC preset marker used by most tests: id 7, 0.15 m, 1.3 m ahead, turned 30/10/15 degrees.
sim::Marker MainMarker();

// ---- template bodies ----

template <class M>
ros::Time Collector<M>::Stamp(const M& msg) {
  return msg.header.stamp;
}

template <>
inline ros::Time Collector<visualization_msgs::MarkerArray>::Stamp(const visualization_msgs::MarkerArray& msg) {
  return msg.markers.empty() ? ros::Time() : msg.markers.front().header.stamp;
}

template <class M>
boost::shared_ptr<const M> Collector<M>::Wait(const ros::Time& stamp, double timeout) const {
  WaitUntil([&] { return First(stamp) != nullptr; }, timeout);
  return First(stamp);
}

template <class M>
boost::shared_ptr<const M> Rig::PublishUntil(const Scene& scene, const Collector<M>& out, const Channels& channels,
                                            double timeout, double period) {
  std::vector<ros::Time> stamps;
  const ros::WallTime end = ros::WallTime::now() + ros::WallDuration(timeout);
  while (ros::ok() && ros::WallTime::now() < end) {
    stamps.push_back(Publish(scene, channels));
    boost::shared_ptr<const M> found;
    const auto answered = [&] {
      for (const auto& stamp : stamps) {
        if ((found = out.First(stamp))) return true;
      }
      return false;
    };
    if (WaitUntil(answered, period)) return found;
  }
  return nullptr;
}

}  // namespace arucotag::test

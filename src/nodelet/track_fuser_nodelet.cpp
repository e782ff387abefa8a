// The track fuser nodelet: one TagTracker fed by several detectors' `tags` (each with ~output_frame
// set to one fixed frame), so a marker that two cameras see is one track. Publishes `tracks`,
// `track_markers` and TF from validated tracks. Wiring only: the tracker is the core's, the
// conversions are tracks.cpp's, the parameters parameters.cpp's. Every callback runs on the
// nodelet's single-threaded queue.
#include <arucotag/ros/conversions.hpp>  // first: it renames the generated ArucoTag message
#include <arucotag/ros/parameters.hpp>
#include <arucotag/ros/tracks.hpp>

#include <map>
#include <memory>
#include <string>
#include <vector>

#include <nodelet/nodelet.h>
#include <pluginlib/class_list_macros.hpp>
#include <tf2_ros/transform_broadcaster.h>

namespace arucotag {

namespace {
constexpr double kThrottle = 5.0;  // s between repeats of one kind of error
}  // namespace

class TrackFuserNodelet : public nodelet::Nodelet {
 private:
  void onInit() override;
  void OnTags(const ArucoTagArrayConstPtr& tags, const std::string& topic);
  void PublishTf(const TagTracks& tracks);

  FuserParameters params_;
  std::unique_ptr<TagTracker> tracker_;
  std::map<std::uint32_t, ros::Time> last_seen_;  // per track id: the exact stamp of its last hit
  ros::Time latest_;                              // the tracker's latest stamp, exact
  std::size_t resets_ = 0;                        // the tracker's resets seen so far
  std::map<std::string, ros::Time> last_tf_stamp_;  // per child frame: TF never gets one stamp twice

  std::vector<ros::Subscriber> subs_;
  ros::Publisher tracks_pub_, track_markers_pub_;
  std::unique_ptr<tf2_ros::TransformBroadcaster> tf_broadcaster_;
};

void TrackFuserNodelet::onInit() {
  ros::NodeHandle& nh = getNodeHandle();
  const ros::NodeHandle& pnh = getPrivateNodeHandle();
  try {
    params_ = ReadFuserParameters(pnh);
    tracker_ = std::make_unique<TagTracker>(params_.tracker);
  } catch (const std::exception& e) {
    // Never throw out of onInit: the manager and its other nodelets keep running.
    NODELET_ERROR("%s; this nodelet stays inert (nothing subscribed or published) until it is reloaded with valid "
                  "parameters",
                  e.what());
    return;
  }
  for (const auto& name : UnknownFuserParameters(pnh)) {
    NODELET_WARN("unknown parameter ~%s is ignored (typo?); the README's \"Fusing cameras\" lists the valid ones",
                 name.c_str());
  }
  if (params_.publish_tf) tf_broadcaster_ = std::make_unique<tf2_ros::TransformBroadcaster>();
  tracks_pub_ = nh.advertise<TagTracks>("tracks", 10);
  track_markers_pub_ = nh.advertise<visualization_msgs::MarkerArray>("track_markers", 1);
  for (const auto& input : params_.inputs) {
    const std::string topic = nh.resolveName(input);
    subs_.push_back(nh.subscribe<ArucoTagArray>(
        topic, static_cast<uint32_t>(params_.queue_size),
        [this, topic](const ArucoTagArrayConstPtr& tags) { OnTags(tags, topic); }));
  }
  NODELET_INFO("fusing the tracks of %zu tag topics in %s, publishing %s", params_.inputs.size(),
               params_.fixed_frame.c_str(), nh.resolveName("tracks").c_str());
}

void TrackFuserNodelet::OnTags(const ArucoTagArrayConstPtr& tags, const std::string& topic) {
  const std::string& frame = tags->header.frame_id;
  if (frame != params_.fixed_frame) {
    if (frame.empty() || frame == tags->camera_frame_id) {
      NODELET_ERROR_THROTTLE(kThrottle,
                             "tags on %s are in their camera's own frame '%s' (no ~output_frame on that detector): "
                             "camera-frame poses move with the camera and cannot be fused; set the detector's "
                             "~output_frame to %s. Message refused",
                             topic.c_str(), frame.c_str(), params_.fixed_frame.c_str());
    } else {
      NODELET_ERROR_THROTTLE(kThrottle,
                             "tags on %s are in frame '%s', the fuser fuses in '%s' (~output_frame): set the "
                             "detector's ~output_frame to %s. Message refused",
                             topic.c_str(), frame.c_str(), params_.fixed_frame.c_str(), params_.fixed_frame.c_str());
    }
    return;
  }
  // Messages from before camera_frame_id existed still fuse, under their topic's name.
  const std::string& camera = tags->camera_frame_id.empty() ? topic : tags->camera_frame_id;
  tracker_->Update(camera, tags->header.stamp.toSec(), MeasurementsFromMessage(*tags));
  // Cameras' messages interleave: the tracks stand at the latest stamp any camera has reached
  // (the tracker predicts to it), unless the tracker restarted on a stamp far back (a bag loop).
  const bool reset = tracker_->Counts().resets != resets_;
  resets_ = tracker_->Counts().resets;
  if (reset || tags->header.stamp > latest_) latest_ = tags->header.stamp;
  std_msgs::Header header = tags->header;
  header.stamp = latest_;
  const TagTracks tracks = ToMessage(*tracker_, header, tags->header.stamp, last_seen_);
  tracks_pub_.publish(tracks);
  if (track_markers_pub_.getNumSubscribers() > 0) track_markers_pub_.publish(ToTrackMarkers(tracks));
  if (tf_broadcaster_) PublishTf(tracks);
}

void TrackFuserNodelet::PublishTf(const TagTracks& tracks) {
  std_msgs::Header header = tracks.header;
  if (header.stamp.isZero()) header.stamp = ros::Time::now();
  std::vector<geometry_msgs::TransformStamped> transforms;
  for (const auto& [id, pose] : ValidatedPoses(tracks)) {
    const std::string child = params_.frame_prefix + std::to_string(id);
    ros::Time& last = last_tf_stamp_[child];
    if (last == header.stamp) continue;  // the other camera's message at this stamp: TF would reject a repeat
    last = header.stamp;
    transforms.push_back(ToTransform(pose, header, child));
  }
  if (!transforms.empty()) tf_broadcaster_->sendTransform(transforms);
}

}  // namespace arucotag

PLUGINLIB_EXPORT_CLASS(arucotag::TrackFuserNodelet, nodelet::Nodelet)

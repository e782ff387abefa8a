// Rostest (fuser.test): two cameras' detectors and arucotag/TrackFuser in one manager, started by the
// shipped launch/fuser.launch. Both cameras see the real photo of markers 245 and 246
// (UbiquityRobotics/fiducials, tag_245-246_d7_14cm.png) at unsynchronized stamps: front_optical as
// shot, rear_optical rolled 180 degrees about the same optical axis, so it sees the photo upside down
// under the calibration that goes with that. Static TFs put both in odom. The fused tracks must hold
// one validated track per marker fed by both cameras, at the photo's reference pose in odom, with a
// covariance below each camera's own track's; a message in another frame, or in its camera's own
// frame, is refused with an error and the fuser keeps fusing.
#include <algorithm>
#include <cstdio>
#include <mutex>
#include <set>
#include <string>
#include <vector>

#include <arucotag/TagTracks.h>
#include <nodelet/NodeletList.h>
#include <opencv2/core.hpp>
#include <ros/master.h>
#include <rosgraph_msgs/Log.h>
#include <tf2/LinearMath/Matrix3x3.h>
#include <tf2/LinearMath/Quaternion.h>
#include <tf2_geometry_msgs/tf2_geometry_msgs.h>
#include <tf2_ros/static_transform_broadcaster.h>

#include "photos.hpp"
#include "rig.hpp"

namespace arucotag::test {
namespace {

using TagArray = arucotag::ArucoTagArray;
using TagMsg = arucotag::ArucoTag;

constexpr const char* kFront = "front_optical";
constexpr const char* kRear = "rear_optical";
constexpr int kFrames = 6;
constexpr double kPeriod = 0.1;      // s between a camera's frames
constexpr double kRearOffset = 0.037;  // s: the cameras are not synchronized

// odom <- front_optical: 1 m up, 2 m ahead, the optical axis along odom x.
const cv::Matx33d kOdomFront(0, 0, 1, -1, 0, 0, 0, -1, 0);
const cv::Vec3d kOdomFrontTranslation(2.0, 0.0, 1.0);
// front_optical <- rear_optical: rolled half a turn about the optical axis.
const cv::Matx33d kFrontRear(-1, 0, 0, 0, -1, 0, 0, 0, 1);

// The photo as the rolled camera sees it: every pixel (and reference corner) at (W-1-x, H-1-y).
const Photo& UpsideDown() {
  static const Photo photo = [] {
    const Photo& upright = TwoTags();
    Photo rolled;
    cv::rotate(upright.bgr, rolled.bgr, cv::ROTATE_180);
    const cv::Point2d last(upright.bgr.cols - 1, upright.bgr.rows - 1);
    for (const auto& [id, quad] : upright.corners) {
      for (int i = 0; i < 4; ++i) rolled.corners[id][i] = last - quad[i];
    }
    return rolled;
  }();
  return photo;
}

// The calibration of the rolled camera: the principal point mirrored through the image centre,
// the normalized coordinates negated, so the tangential terms change sign.
cv::Matx33d RearK() {
  cv::Matx33d k = kPhotoK;
  k(0, 2) = 1279.0 - k(0, 2);
  k(1, 2) = 959.0 - k(1, 2);
  return k;
}
std::vector<double> RearD() { return {kPhotoD[0], kPhotoD[1], -kPhotoD[2], -kPhotoD[3], kPhotoD[4]}; }

geometry_msgs::TransformStamped Static(const std::string& child, const cv::Matx33d& r, const cv::Vec3d& t) {
  geometry_msgs::TransformStamped tf;
  tf.header.frame_id = "odom";
  tf.child_frame_id = child;
  tf2::Quaternion q;
  tf2::Matrix3x3(r(0, 0), r(0, 1), r(0, 2), r(1, 0), r(1, 1), r(1, 2), r(2, 0), r(2, 1), r(2, 2)).getRotation(q);
  tf.transform.rotation = tf2::toMsg(q);
  tf.transform.translation.x = t[0];
  tf.transform.translation.y = t[1];
  tf.transform.translation.z = t[2];
  return tf;
}

// Sum of the position (or rotation) variances of a row-major 6x6 covariance.
template <class C>
double Trace3(const C& c, int first) {
  return c[first * 7] + c[(first + 1) * 7] + c[(first + 2) * 7];
}

const TagTrack* Find(const TagTracks& tracks, int id) {
  const auto it = std::find_if(tracks.tracks.begin(), tracks.tracks.end(), [id](const TagTrack& t) { return t.id == id; });
  return it == tracks.tracks.end() ? nullptr : &*it;
}

struct Camera {
  Camera(ros::NodeHandle& nh, const std::string& ns)
      : image(nh.advertise<sensor_msgs::Image>("/" + ns + "/image", 10)),
        info(nh.advertise<sensor_msgs::CameraInfo>("/" + ns + "/camera_info", 10, true)),
        tags(nh, "/" + ns + "/tags"),
        tracks(nh, "/" + ns + "/tracks") {}
  ros::Publisher image, info;
  Collector<TagArray> tags;
  Collector<TagTracks> tracks;
};

ros::NodeHandle* nh = nullptr;
Camera* front = nullptr;
Camera* rear = nullptr;
Collector<TagTracks>* fused = nullptr;
ros::Time last_stamp;

bool Ready() {
  return WaitUntil([] { return front->image.getNumSubscribers() > 0 && rear->image.getNumSubscribers() > 0 &&
                               fused->Publishers() > 0 && front->tags.Publishers() > 0 && rear->tags.Publishers() > 0; },
                   30.0);
}

TEST(TrackFuser, OneValidatedTrackPerMarkerFromBothCameras) {
  tf2_ros::StaticTransformBroadcaster statics;
  statics.sendTransform(std::vector<geometry_msgs::TransformStamped>{
      Static(kFront, kOdomFront, kOdomFrontTranslation),
      Static(kRear, kOdomFront * kFrontRear, kOdomFrontTranslation)});
  ASSERT_TRUE(Ready());
  const ros::Time start = ros::Time::now();
  front->info.publish(RaspiInfo(start, kFront));
  rear->info.publish(RaspiInfo(start, kRear, RearK(), RearD()));
  ros::WallDuration(0.5).sleep();  // camera_info and the static TFs reach the detectors

  ros::Time front_stamp, rear_stamp;
  for (int i = 0; i < kFrames; ++i) {
    front_stamp = start + ros::Duration(kPeriod * (i + 1));
    rear_stamp = front_stamp + ros::Duration(kRearOffset);
    front->image.publish(PhotoImage(TwoTags(), front_stamp, kFront));
    rear->image.publish(PhotoImage(UpsideDown(), rear_stamp, kRear));
    const auto front_tags = front->tags.Wait(front_stamp, 10.0);
    const auto rear_tags = rear->tags.Wait(rear_stamp, 10.0);
    ASSERT_TRUE(front_tags && rear_tags) << "frame " << i;
    for (const auto& tags : {front_tags, rear_tags}) {
      EXPECT_EQ(tags->header.frame_id, "odom");
      ASSERT_EQ(tags->tags.size(), 2u) << tags->camera_frame_id << " frame " << i;
      for (const auto& tag : tags->tags) EXPECT_NE(tag.pose_source, TagMsg::NONE);
    }
    EXPECT_EQ(front_tags->camera_frame_id, kFront);
    EXPECT_EQ(rear_tags->camera_frame_id, kRear);
  }
  last_stamp = rear_stamp;

  // The fuser's answer once both cameras' last frames are in: stamped with the latest stamp.
  const auto complete = [&](const boost::shared_ptr<const TagTracks>& msg) {
    return msg->tracks.size() == 2 && std::all_of(msg->tracks.begin(), msg->tracks.end(), [](const TagTrack& t) {
             return t.hits == 2 * kFrames;
           });
  };
  boost::shared_ptr<const TagTracks> msg;
  WaitUntil([&] {
    for (const auto& m : fused->At(rear_stamp)) {
      if (complete(m)) msg = m;
    }
    return msg != nullptr;
  }, 10.0);
  ASSERT_TRUE(msg) << "no fused tracks at " << rear_stamp << " holding both cameras' " << kFrames << " frames";
  const auto front_tracks = front->tracks.Wait(front_stamp, 5.0);
  const auto rear_tracks = rear->tracks.Wait(rear_stamp, 5.0);
  ASSERT_TRUE(front_tracks && rear_tracks);

  EXPECT_EQ(msg->header.frame_id, "odom");
  for (const auto& [id, corners] : TwoTags().corners) {
    SCOPED_TRACE("marker " + std::to_string(id));
    const TagTrack* track = Find(*msg, id);
    ASSERT_NE(track, nullptr);
    EXPECT_TRUE(track->validated);
    EXPECT_TRUE(track->filtered);
    EXPECT_EQ(track->misses, 0u);
    EXPECT_EQ(track->outliers, 0u) << "the two cameras' detections agree within their covariances";
    EXPECT_EQ(std::set<std::string>(track->cameras.begin(), track->cameras.end()),
              (std::set<std::string>{kFront, kRear}));
    EXPECT_EQ(track->last_seen, rear_stamp);

    // Truth: the photo's reference corners under each camera's calibration, moved into odom.
    cv::Matx33d rotation, rear_rotation;
    cv::Vec3d position, rear_position;
    ReferencePose(corners, rotation, position);
    ReferencePose(UpsideDown().corners.at(id), rear_rotation, rear_position, RearK(), RearD());
    const cv::Vec3d truth = kOdomFront * position + kOdomFrontTranslation;
    ASSERT_LT(cv::norm(kOdomFront * kFrontRear * rear_position + kOdomFrontTranslation - truth), 1e-3)
        << "the rear camera's geometry must put the marker where the front one sees it";
    EXPECT_TRUE(PoseMatches(track->pose.pose, kOdomFront * rotation, truth, cv::norm(position)));

    // One camera alone: its own detector's track, one camera listed; the fused one holds both.
    const TagTrack* alone_front = Find(*front_tracks, id);
    const TagTrack* alone_rear = Find(*rear_tracks, id);
    ASSERT_TRUE(alone_front && alone_rear);
    EXPECT_EQ(alone_front->cameras, std::vector<std::string>{kFront});
    EXPECT_EQ(alone_rear->cameras, std::vector<std::string>{kRear});
    EXPECT_EQ(alone_front->hits, static_cast<uint32_t>(kFrames));
    for (int block : {0, 3}) {
      const double fused_variance = Trace3(track->pose.covariance, block);
      const double best_alone = std::min(Trace3(alone_front->pose.covariance, block),
                                         Trace3(alone_rear->pose.covariance, block));
      // Two cameras seeing the marker equally well, no process noise (fuser.test): about half of one
      // camera's variance.
      std::printf("marker %d %s variance: fused %.3g, front alone %.3g, rear alone %.3g\n", id,
                  block ? "rotation" : "position", fused_variance, Trace3(alone_front->pose.covariance, block),
                  Trace3(alone_rear->pose.covariance, block));
      EXPECT_LT(fused_variance, 0.75 * best_alone) << (block ? "rotation" : "position") << " variance";
      EXPECT_GT(fused_variance, 0.25 * best_alone) << (block ? "rotation" : "position") << " variance";
    }
  }
}

// How many nodes the master lists as publishers of `topic` (-1 when it cannot be asked).
int RegisteredPublishers(const std::string& topic) {
  XmlRpc::XmlRpcValue args, result, payload;
  args[0] = ros::this_node::getName();
  if (!ros::master::execute("getSystemState", args, result, payload, false)) return -1;
  XmlRpc::XmlRpcValue& publishers = payload[0];
  for (int i = 0; i < publishers.size(); ++i) {
    if (static_cast<std::string>(publishers[i][0]) == topic) return publishers[i][1].size();
  }
  return 0;
}

// Tags in another frame, and tags in their camera's own frame, on a third input: each refused with
// an error naming the topic and the cure; no track comes of them and the fuser keeps fusing.
TEST(TrackFuser, RefusesTagsInAnotherFrame) {
  std::mutex mutex;
  std::vector<std::string> errors;
  ros::Subscriber rosout = nh->subscribe<rosgraph_msgs::Log>("/rosout", 100, [&](const rosgraph_msgs::LogConstPtr& log) {
    std::lock_guard<std::mutex> lock(mutex);
    if (log->level == rosgraph_msgs::Log::ERROR && log->msg.find("/wrong/tags") != std::string::npos) {
      errors.push_back(log->msg);
    }
  });
  ros::Publisher wrong = nh->advertise<TagArray>("/wrong/tags", 10);
  // Connected to every node that logs, the fuser's manager among them: one connected late would lose the
  // errors (the sanitizer build's CI run saw one of two).
  ASSERT_TRUE(WaitUntil([&] {
    const int registered = RegisteredPublishers("/rosout");
    return wrong.getNumSubscribers() > 0 && registered > 0 && static_cast<int>(rosout.getNumPublishers()) >= registered;
  }, 20.0)) << rosout.getNumPublishers() << " of " << RegisteredPublishers("/rosout") << " /rosout publishers connected";
  ASSERT_TRUE(Ready());

  TagArray array;
  array.camera_frame_id = "wrong_optical";
  TagMsg tag;
  tag.id = 77;
  tag.side_length = kPhotoSide;
  tag.pose_source = TagMsg::PNP;
  tag.pose.position.x = 2.6;
  tag.pose.orientation.w = 1.0;
  for (int i = 0; i < 6; ++i) tag.covariance[i * 7] = 1e-4;
  array.tags.push_back(tag);

  const ros::Time base = std::max(ros::Time::now(), last_stamp);
  array.header.stamp = base + ros::Duration(0.1);
  array.header.frame_id = "base_link";  // a frame that moves with the rover, not odom
  wrong.publish(array);
  array.header.stamp = base + ros::Duration(0.2);
  array.header.frame_id = array.camera_frame_id;  // a detector without ~output_frame
  array.tags[0].id = 78;
  wrong.publish(array);
  ASSERT_TRUE(WaitUntil([&] {
    std::lock_guard<std::mutex> lock(mutex);
    return errors.size() >= 2;
  }, 10.0)) << "each refused message must be an error naming its topic";
  {
    std::lock_guard<std::mutex> lock(mutex);
    EXPECT_NE(errors[0].find("in frame 'base_link'"), std::string::npos) << errors[0];
    EXPECT_NE(errors[0].find("odom"), std::string::npos) << errors[0];
    EXPECT_NE(errors[1].find("cannot be fused"), std::string::npos) << errors[1];
    EXPECT_NE(errors[1].find("~output_frame"), std::string::npos) << errors[1];
  }
  EXPECT_TRUE(fused->At(base + ros::Duration(0.1)).empty());
  EXPECT_TRUE(fused->At(base + ros::Duration(0.2)).empty());

  // Still fusing: the next photo from the front camera is answered, with the two markers only.
  const ros::Time stamp = base + ros::Duration(0.3);
  front->image.publish(PhotoImage(TwoTags(), stamp, kFront));
  const auto msg = fused->Wait(stamp, 10.0);
  ASSERT_TRUE(msg) << "the fuser must keep running after refusing messages";
  ASSERT_EQ(msg->tracks.size(), 2u);
  for (const auto& track : msg->tracks) {
    EXPECT_TRUE(track.id == 245 || track.id == 246) << "track of refused id " << track.id;
    EXPECT_EQ(track.last_seen, stamp);
  }
}

// A fuser loaded without ~inputs into the same manager stays inert: loaded, nothing advertised,
// while the good fuser beside it answers (the other tests).
TEST(TrackFuser, WithoutInputsItStaysInertAndTheManagerRuns) {
  ASSERT_TRUE(Ready());
  nodelet::NodeletList list;
  ASSERT_TRUE(WaitUntil([&] {
    return ros::service::call("/aruco_manager/list", list) &&
           std::count(list.response.nodelets.begin(), list.response.nodelets.end(), "/bad/fuser") == 1;
  }, 30.0)) << "the bad fuser must be loaded (onInit returned) without taking the manager down";
  ros::master::V_TopicInfo topics;
  ASSERT_TRUE(ros::master::getTopics(topics));
  const auto advertised = [&topics](const std::string& name) {
    return std::any_of(topics.begin(), topics.end(), [&](const ros::master::TopicInfo& t) { return t.name == name; });
  };
  EXPECT_TRUE(advertised("/aruco_fused/tracks"));
  EXPECT_FALSE(advertised("/bad/tracks"));
  EXPECT_FALSE(advertised("/bad/track_markers"));
}

}  // namespace
}  // namespace arucotag::test

int main(int argc, char** argv) {
  testing::InitGoogleTest(&argc, argv);
  ros::init(argc, argv, "test_fuser");
  ros::AsyncSpinner spinner(2);
  spinner.start();
  ros::NodeHandle nh;
  arucotag::test::Camera front(nh, "front"), rear(nh, "rear");
  arucotag::test::Collector<arucotag::TagTracks> fused(nh, "/aruco_fused/tracks");
  arucotag::test::nh = &nh;
  arucotag::test::front = &front;
  arucotag::test::rear = &rear;
  arucotag::test::fused = &fused;
  const int result = RUN_ALL_TESTS();
  spinner.stop();
  return result;
}

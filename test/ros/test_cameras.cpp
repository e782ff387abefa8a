// Rostest (cameras.test): two cameras' detectors in one manager (launch/rover.launch) and a
// detector whose ~output_frame never resolves. Both cameras see marker 7; TF must hold one child
// frame per camera, each with that camera's view of the marker.
#include <map>
#include <mutex>
#include <set>

#include <diagnostic_msgs/DiagnosticArray.h>
#include <tf2_msgs/TFMessage.h>

#include "rig.hpp"

namespace arucotag::test {
namespace {

using TagArray = arucotag::ArucoTagArray;

// One camera's publishers and its detector's tags.
struct Camera {
  Camera(ros::NodeHandle& nh, const std::string& ns)
      : frame(ns + "_camera_optical_frame"),
        image(nh.advertise<sensor_msgs::Image>("/" + ns + "/image", 5)),
        info(nh.advertise<sensor_msgs::CameraInfo>("/" + ns + "/camera_info", 5)),
        cloud(nh.advertise<sensor_msgs::PointCloud2>("/" + ns + "/points", 5)),
        tags(nh, "/" + ns + "/tags") {}

  ros::Time Publish(const Scene& scene, const ros::Time& stamp, bool with_cloud) {
    auto camera_info = Rig::InfoMessage(scene.camera, stamp);
    camera_info->header.frame_id = frame;
    info.publish(camera_info);
    if (with_cloud) {
      cloud.publish(Rig::CloudMessage(scene.cloud, stamp, frame));
      ros::WallDuration(0.03).sleep();
    }
    auto msg = Rig::ImageMessage(scene.image, stamp);
    msg->header.frame_id = frame;
    image.publish(msg);
    return stamp;
  }

  std::string frame;
  ros::Publisher image, info, cloud;
  Collector<TagArray> tags;
};

TEST(Cameras, TwoCamerasNeverPublishTheSameFrame) {
  ros::NodeHandle nh;
  std::mutex mutex;
  std::map<std::string, std::set<std::string>> parents;        // child -> every parent it was given
  std::map<std::pair<std::string, ros::Time>, int> per_stamp;  // (child, stamp) -> transforms sent
  ros::Subscriber tf = nh.subscribe<tf2_msgs::TFMessage>("/tf", 100, [&](const tf2_msgs::TFMessageConstPtr& msg) {
    std::lock_guard<std::mutex> lock(mutex);
    for (const auto& t : msg->transforms) {
      parents[t.child_frame_id].insert(t.header.frame_id);
      ++per_stamp[{t.child_frame_id, t.header.stamp}];
    }
  });
  Camera left(nh, "left"), right(nh, "right");
  // Nodelets in one manager share its connections: one subscriber per topic is the whole manager.
  ASSERT_TRUE(WaitUntil([&] { return left.image.getNumSubscribers() >= 1 && right.image.getNumSubscribers() >= 1 &&
                                     left.cloud.getNumSubscribers() >= 1; },
                        30.0))
      << "rover.launch's detectors never subscribed";
  ros::WallDuration(1.0).sleep();  // every nodelet of the manager has subscribed by now

  // Each camera sees marker 7 from its own place.
  const Scene seen_left = Render({sim::FacingCamera(7, 0.15, {0.2, 0.0, 1.5}, 20.0, 0.0, 0.0)});
  const Scene seen_right = Render({sim::FacingCamera(7, 0.15, {-0.3, 0.1, 2.0}, -15.0, 5.0, 10.0)});
  std::vector<ros::Time> stamps;
  for (int i = 0; i < 10; ++i) {
    const ros::Time stamp = ros::Time::now();
    stamps.push_back(stamp);
    left.Publish(seen_left, stamp, true);
    right.Publish(seen_right, stamp, false);
    ros::WallDuration(0.1).sleep();
  }
  for (const auto& stamp : stamps) {
    const auto l = left.tags.Wait(stamp, 5.0), r = right.tags.Wait(stamp, 5.0);
    ASSERT_TRUE(l && r);
    ASSERT_EQ(l->tags.size(), 1u);
    ASSERT_EQ(r->tags.size(), 1u);
    EXPECT_EQ(l->header.frame_id, left.frame);
    EXPECT_EQ(r->header.frame_id, right.frame);
    EXPECT_EQ(l->tags[0].pose_source, arucotag::ArucoTag::FUSED) << "the stereo camera has a cloud";
    EXPECT_EQ(r->tags[0].pose_source, arucotag::ArucoTag::PNP) << "the mono camera has none";
    EXPECT_TRUE(PoseMatches(l->tags[0].pose, seen_left.markers[0]));
    EXPECT_TRUE(PoseMatches(r->tags[0].pose, seen_right.markers[0]));
  }
  ros::WallDuration(0.5).sleep();

  std::lock_guard<std::mutex> lock(mutex);
  const std::string left_child = left.frame + "/aruco_7", right_child = right.frame + "/aruco_7";
  ASSERT_TRUE(parents.count(left_child)) << "no TF " << left_child;
  ASSERT_TRUE(parents.count(right_child)) << "no TF " << right_child;
  EXPECT_FALSE(parents.count("aruco_7")) << "bare child frames clash between cameras";
  for (const auto& [child, from] : parents) {
    EXPECT_EQ(from.size(), 1u) << child << " was published by more than one camera";
  }
  for (const auto& stamp : stamps) {
    EXPECT_EQ((per_stamp[{left_child, stamp}]), 1);
    EXPECT_EQ((per_stamp[{right_child, stamp}]), 1);
  }
}

// ~output_frame without a transform: the frames are dropped (never sent in the optical frame) and
// counted in diagnostics.
TEST(Cameras, OutputFrameWithoutTransformPublishesNothing) {
  ros::NodeHandle nh;
  Collector<TagArray> lost(nh, "/lost/tags");
  std::mutex mutex;
  std::map<std::string, std::string> values;
  ros::Subscriber diagnostics = nh.subscribe<diagnostic_msgs::DiagnosticArray>(
      "/diagnostics", 10, [&](const diagnostic_msgs::DiagnosticArrayConstPtr& msg) {
        for (const auto& status : msg->status) {
          if (status.name != "lost/detector: detector") continue;
          std::lock_guard<std::mutex> lock(mutex);
          for (const auto& kv : status.values) values[kv.key] = kv.value;
        }
      });
  Camera left(nh, "left");
  ASSERT_TRUE(WaitUntil([&] { return left.image.getNumSubscribers() >= 1; }, 30.0));
  ros::WallDuration(1.0).sleep();
  const Scene scene = Render({MainMarker()});
  std::vector<ros::Time> stamps;
  for (int i = 0; i < 8; ++i) {
    stamps.push_back(left.Publish(scene, ros::Time::now(), false));
    ros::WallDuration(0.1).sleep();
  }
  const std::string key = "frames dropped (no output_frame transform)";
  ASSERT_TRUE(WaitUntil(
      [&] {
        std::lock_guard<std::mutex> lock(mutex);
        return values.count(key) && std::stoi(values[key]) >= 6;
      },
      10.0))
      << "dropped frames must be counted";
  for (const auto& stamp : stamps) EXPECT_FALSE(lost.First(stamp)) << "a frame went out in another frame";
  std::lock_guard<std::mutex> lock(mutex);
  EXPECT_NE(values["last warning"].find("no_such_frame"), std::string::npos) << values["last warning"];
}

}  // namespace
}  // namespace arucotag::test

int main(int argc, char** argv) {
  testing::InitGoogleTest(&argc, argv);
  ros::init(argc, argv, "test_cameras");
  ros::AsyncSpinner spinner(2);
  spinner.start();
  const int result = RUN_ALL_TESTS();
  spinner.stop();
  return result;
}

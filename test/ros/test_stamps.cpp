// Rostest (stamps.test): the stamp patterns real drivers and bags produce, each on its own detector
// instance, fed with real photos (UbiquityRobotics/fiducials' Raspberry Pi shots, 1280x960,
// DICT_5X5_1000, 0.145 m markers) under the camera's real calibration. Every answer is checked
// against the photos' own answers: the ids, the corners their suite asserts, and the pose those
// corners give under that calibration.
#include <array>
#include <cstdlib>
#include <fstream>
#include <map>
#include <string>

#include <opencv2/calib3d.hpp>
#include <opencv2/imgcodecs.hpp>
#include <arucotag/TagTracks.h>
#include <rosbag/bag.h>
#include <tf2_msgs/TFMessage.h>
#include <tf2_ros/static_transform_broadcaster.h>

#include "photos.hpp"
#include "rig.hpp"

namespace arucotag::test {
namespace {

using TagArray = arucotag::ArucoTagArray;
using TagMsg = arucotag::ArucoTag;

// Ids exactly the photo's, every corner within 1 px of the upstream answer (OpenCV's sub-pixel corners; our edge
// fit differs from them by up to 0.52 px on these photos) and, when a pose is
// expected, the reference pose within 0.5 % of range and 1 degree.
::testing::AssertionResult MatchesPhoto(const TagArray& msg, const Photo& photo, bool with_pose) {
  if (msg.tags.size() != photo.corners.size()) {
    return ::testing::AssertionFailure() << msg.tags.size() << " tags, the photo has " << photo.corners.size();
  }
  for (const auto& tag : msg.tags) {
    const auto truth = photo.corners.find(tag.id);
    if (truth == photo.corners.end()) return ::testing::AssertionFailure() << "id " << tag.id << " is not in the photo";
    for (int i = 0; i < 4; ++i) {
      const double error = std::hypot(tag.corners[i].x - truth->second[i].x, tag.corners[i].y - truth->second[i].y);
      if (error > 1.0) {
        return ::testing::AssertionFailure() << "id " << tag.id << " corner " << i << " is " << error << " px off";
      }
    }
    if (!with_pose) continue;
    if (tag.pose_source == TagMsg::NONE) return ::testing::AssertionFailure() << "id " << tag.id << " has no pose";
    cv::Matx33d rotation;
    cv::Vec3d position;
    ReferencePose(truth->second, rotation, position);
    const auto pose = PoseMatches(tag.pose, rotation, position, cv::norm(position));
    if (!pose) return ::testing::AssertionFailure() << "id " << tag.id << ": " << pose.message();
  }
  return ::testing::AssertionSuccess();
}

// As raspicam_node sends it: a jpeg, format "jpeg".
sensor_msgs::CompressedImagePtr PhotoJpeg(const Photo& photo, const ros::Time& stamp) {
  auto jpeg = boost::make_shared<sensor_msgs::CompressedImage>();
  jpeg->header.stamp = stamp;
  jpeg->header.frame_id = kPhotoFrame;
  jpeg->format = "jpeg";
  cv::imencode(".jpg", photo.bgr, jpeg->data, {cv::IMWRITE_JPEG_QUALITY, 95});
  return jpeg;
}

// An organized cloud that agrees with the photo: each marker's reference plane inside a square
// 1.4 sides wide around it, a wall 1.5 m away elsewhere. `factor` = image pixels per cloud point
// (a depth camera at a fraction of the image resolution).
sensor_msgs::PointCloud2Ptr PhotoCloud(const Photo& photo, const ros::Time& stamp, int factor) {
  static std::map<int, cv::Mat> made;
  cv::Mat& points = made[factor];
  if (points.empty()) {
    std::vector<sim::Marker> markers;
    for (const auto& [id, corners] : photo.corners) {
      cv::Matx33d r;
      sim::Marker m;
      m.id = id;
      m.side = kPhotoSide;
      ReferencePose(corners, r, m.tvec);
      cv::Rodrigues(r, m.rvec);
      markers.push_back(m);
    }
    points = sim::MarkerPlanesCloud(kPhotoK, kPhotoD, photo.bgr.size(), factor, markers, 1.5);
  }
  return Rig::CloudMessage(points, stamp, kPhotoFrame);
}

// One pattern's detector: its inputs under /<ns>, its tags collected by stamp, in arrival order.
struct Instance {
  explicit Instance(ros::NodeHandle& nh, const std::string& ns, bool latched_info = false)
      : ns(ns),
        image(nh.advertise<sensor_msgs::Image>("/" + ns + "/image", 30)),
        info(nh.advertise<sensor_msgs::CameraInfo>("/" + ns + "/camera_info", 30, latched_info)),
        cloud(nh.advertise<sensor_msgs::PointCloud2>("/" + ns + "/points", 30)),
        tags(nh, "/" + ns + "/tags"),
        sub(nh.subscribe<TagArray>("/" + ns + "/tags", 100, [this](const boost::shared_ptr<const TagArray>& msg) {
          std::lock_guard<std::mutex> lock(mutex);
          arrivals.push_back({msg, ros::WallTime::now()});
        })) {}

  // The detector takes all three inputs and both tags subscribers are connected to it: an answer
  // published before the connection is made would be lost (frame 0 of CameraInfoStampedOneSecondBefore
  // went unanswered once in a workspace run).
  bool Ready() const {
    return WaitUntil([&] { return image.getNumSubscribers() > 0 && info.getNumSubscribers() > 0 &&
                                  cloud.getNumSubscribers() > 0 && tags.Publishers() > 0 &&
                                  sub.getNumPublishers() > 0; },
                     30.0);
  }
  size_t Count() const {
    std::lock_guard<std::mutex> lock(mutex);
    return arrivals.size();
  }
  std::vector<std::pair<boost::shared_ptr<const TagArray>, ros::WallTime>> All() const {
    std::lock_guard<std::mutex> lock(mutex);
    return arrivals;
  }

  std::string ns;
  ros::Publisher image, info, cloud;
  Collector<TagArray> tags;
  mutable std::mutex mutex;
  std::vector<std::pair<boost::shared_ptr<const TagArray>, ros::WallTime>> arrivals;
  ros::Subscriber sub;
};

ros::NodeHandle* nh = nullptr;

std::string TempBag(const std::string& name) {
  return (std::getenv("ROS_LOG_DIR") ? std::string(std::getenv("ROS_LOG_DIR")) : std::string("/tmp")) + "/" + name +
         "_" + std::to_string(::getpid()) + ".bag";
}

int Play(const std::string& args) {
  const std::string command = "rosbag play -q " + args + " > /dev/null 2>&1";
  return std::system(command.c_str());
}

// A real single-frame recording: one CompressedImage, its camera_info stamped and recorded half a
// second later, under topic names without a leading slash.
TEST(StampPatterns, BagWithASingleCompressedImage) {
  Instance single(*nh, "single_bag");
  ASSERT_TRUE(WaitUntil([&] { return single.tags.Publishers() > 0; }, 30.0));
  const std::string path = TempBag("single");
  const ros::Time stamp(1500000000, 250000000);
  {
    rosbag::Bag bag(path, rosbag::bagmode::Write);
    bag.write("single_bag/image/compressed", stamp, *PhotoJpeg(OneTag(), stamp));
    const ros::Time info_stamp = stamp + ros::Duration(0.5);
    bag.write("single_bag/camera_info", info_stamp, *RaspiInfo(info_stamp));
  }
  ASSERT_EQ(Play("-d 1 " + path), 0);
  const auto msg = single.tags.Wait(stamp, 5.0);
  ASSERT_TRUE(msg) << "the single frame must be answered";
  EXPECT_EQ(msg->header.frame_id, kPhotoFrame);
  EXPECT_TRUE(MatchesPhoto(*msg, OneTag(), true)) << "camera_info came after the image: the image waits for it";
  EXPECT_EQ(single.Count(), 1u);
  std::remove(path.c_str());
}

TEST(StampPatterns, CameraInfoOnceLatched) {
  Instance latched(*nh, "latched", true);
  ASSERT_TRUE(latched.Ready());
  latched.info.publish(RaspiInfo(ros::Time::now() - ros::Duration(30.0)));  // once, long before
  ros::WallDuration(0.3).sleep();
  for (int i = 0; i < 5; ++i) {
    const ros::Time stamp = ros::Time::now();
    latched.image.publish(PhotoImage(TwoTags(), stamp));
    const auto msg = latched.tags.Wait(stamp, 5.0);
    ASSERT_TRUE(msg) << "frame " << i;
    EXPECT_TRUE(MatchesPhoto(*msg, TwoTags(), true)) << "frame " << i;
    ros::WallDuration(0.05).sleep();
  }
}

// camera_info stamped a second away from each image, sent before (info_before) or after it.
void InfoOffset(const std::string& ns, double offset) {
  Instance instance(*nh, ns);
  ASSERT_TRUE(instance.Ready());
  for (int i = 0; i < 5; ++i) {
    const ros::Time stamp = ros::Time::now();
    if (offset < 0.0) instance.info.publish(RaspiInfo(stamp + ros::Duration(offset)));
    instance.image.publish(PhotoImage(TwoTags(), stamp));
    if (offset > 0.0) {
      ros::WallDuration(0.1).sleep();
      instance.info.publish(RaspiInfo(stamp + ros::Duration(offset)));
    }
    const auto msg = instance.tags.Wait(stamp, 5.0);
    ASSERT_TRUE(msg) << "frame " << i;
    EXPECT_TRUE(MatchesPhoto(*msg, TwoTags(), true)) << "frame " << i;
    ros::WallDuration(0.1).sleep();
  }
}

TEST(StampPatterns, CameraInfoStampedOneSecondBefore) { InfoOffset("info_before", -1.0); }
TEST(StampPatterns, CameraInfoStampedOneSecondAfterAndSentLate) { InfoOffset("info_after", 1.0); }

// TF listeners reject a second transform at one stamp: it goes out once, the tags every time.
TEST(StampPatterns, RepeatedIdenticalStamps) {
  Instance repeated(*nh, "repeated");
  ASSERT_TRUE(repeated.Ready());
  std::mutex mutex;
  std::map<std::string, int> sent;
  ros::Subscriber tf = nh->subscribe<tf2_msgs::TFMessage>("/tf", 100, [&](const tf2_msgs::TFMessageConstPtr& msg) {
    std::lock_guard<std::mutex> lock(mutex);
    for (const auto& t : msg->transforms) ++sent[t.child_frame_id + "@" + std::to_string(t.header.stamp.toNSec())];
  });
  ros::WallDuration(0.5).sleep();
  const ros::Time stamp = ros::Time::now();
  repeated.info.publish(RaspiInfo(stamp));
  for (int i = 0; i < 4; ++i) {
    repeated.image.publish(PhotoImage(TwoTags(), stamp));
    ros::WallDuration(0.15).sleep();
  }
  ASSERT_TRUE(WaitUntil([&] { return repeated.tags.At(stamp).size() == 4; }, 5.0))
      << repeated.tags.At(stamp).size() << " of 4 frames answered";
  for (const auto& msg : repeated.tags.At(stamp)) EXPECT_TRUE(MatchesPhoto(*msg, TwoTags(), true));
  ros::WallDuration(0.3).sleep();
  std::lock_guard<std::mutex> lock(mutex);
  for (int id : {245, 246}) {
    const std::string key = std::string(kPhotoFrame) + "/aruco_" + std::to_string(id) + "@" + std::to_string(stamp.toNSec());
    EXPECT_EQ(sent[key], 1) << key;
  }
}

TEST(StampPatterns, ZeroStamps) {
  Instance zero(*nh, "zero");
  ASSERT_TRUE(zero.Ready());
  zero.info.publish(RaspiInfo(ros::Time()));
  ros::WallDuration(0.2).sleep();
  for (int i = 0; i < 3; ++i) {
    const size_t before = zero.tags.At(ros::Time()).size();
    zero.image.publish(PhotoImage(TwoTags(), ros::Time()));
    ASSERT_TRUE(WaitUntil([&] { return zero.tags.At(ros::Time()).size() > before; }, 5.0)) << "frame " << i;
    EXPECT_TRUE(MatchesPhoto(*zero.tags.At(ros::Time()).back(), TwoTags(), true)) << "frame " << i;
  }
}

// rosbag play -l: stamps jump back at every loop; the detector keeps answering every frame.
TEST(StampPatterns, LoopingBag) {
  Instance loop(*nh, "loop");
  ASSERT_TRUE(loop.Ready());
  const std::string path = TempBag("loop");
  std::vector<ros::Time> stamps;
  {
    rosbag::Bag bag(path, rosbag::bagmode::Write);
    const ros::Time start(1600000000, 0);
    bag.write("/loop/camera_info", start, *RaspiInfo(start));
    for (int i = 0; i < 3; ++i) {
      const ros::Time stamp = start + ros::Duration(0.1 * i);
      stamps.push_back(stamp);
      bag.write("/loop/image/compressed", stamp, *PhotoJpeg(TwoTags(), stamp));
    }
  }
  // Three frames in 0.3 s, looped for 2.5 s: about eight loops.
  EXPECT_NE(Play("-d 1 -l " + path + " & pid=$!; sleep 3.5; kill -INT $pid; wait $pid"), -1);
  const auto all = loop.All();
  EXPECT_GE(all.size(), 9u) << "at least three loops of three frames";
  for (const auto& stamp : stamps) EXPECT_GE(loop.tags.At(stamp).size(), 3u) << "every frame on every loop";
  for (const auto& [msg, when] : all) EXPECT_TRUE(MatchesPhoto(*msg, TwoTags(), true));
  std::remove(path.c_str());
}

// A stereo cloud with every third image (at half the image resolution): no image waits or is
// dropped, and those near a cloud in stamp use it.
TEST(StampPatterns, CloudsAtAThirdOfTheImageRate) {
  Instance third(*nh, "cloud_third");
  ASSERT_TRUE(third.Ready());
  std::vector<ros::Time> stamps;
  const ros::Time start = ros::Time::now();
  third.info.publish(RaspiInfo(start));
  ros::WallDuration(0.1).sleep();
  for (int i = 0; i < 30; ++i) {
    const ros::Time stamp = start + ros::Duration(i / 30.0);
    stamps.push_back(stamp);
    if (i % 3 == 0) {
      third.cloud.publish(PhotoCloud(TwoTags(), stamp, 2));
      ros::WallDuration(0.01).sleep();
    }
    const ros::WallTime sent = ros::WallTime::now();
    third.image.publish(PhotoImage(TwoTags(), stamp));
    // Stamps 1/30 s apart, sent at 30 Hz, but never faster than the detector answers: what is checked
    // here is the pairing by stamp, not throughput (make soak measures that), and the sanitizer build
    // takes longer than a frame period on this photo, so its input queue would drop frames.
    WaitUntil([&] { return third.Count() > static_cast<size_t>(i); }, 2.0);
    const ros::WallDuration left = ros::WallDuration(1.0 / 30.0) - (ros::WallTime::now() - sent);
    if (left > ros::WallDuration(0)) left.sleep();
  }
  ASSERT_TRUE(WaitUntil([&] { return third.Count() >= stamps.size(); }, 10.0)) << third.Count() << " of 30 answered";
  int fused = 0;
  for (const auto& stamp : stamps) {
    const auto msg = third.tags.First(stamp);
    ASSERT_TRUE(msg);
    EXPECT_TRUE(MatchesPhoto(*msg, TwoTags(), true));
    for (const auto& tag : msg->tags) {
      if (tag.pose_source == TagMsg::FUSED) {
        ++fused;
        EXPECT_GT(tag.cloud_points, 100) << "the half-resolution cloud is used at image resolution";
      }
    }
  }
  EXPECT_GE(fused, 2 * 24) << "at least 24 of 30 frames (2 tags each) paired with a cloud within 0.1 s";
}

// Clouds sent 100 ms after their image: images are answered at once, not held for their cloud.
TEST(StampPatterns, CloudsArriving100MsLate) {
  Instance late(*nh, "cloud_late");
  ASSERT_TRUE(late.Ready());
  const ros::Time start = ros::Time::now();
  late.info.publish(RaspiInfo(start));
  ros::WallDuration(0.1).sleep();
  // How long this build takes to answer a frame without a cloud (the sanitizer build: about 0.1 s on
  // this photo). Each cloud goes out 100 ms after its image, or three such answers when that is longer,
  // so that "answered before its cloud" tells an image that waited for its cloud from one that did not.
  const ros::WallTime probe_sent = ros::WallTime::now();
  late.image.publish(PhotoImage(TwoTags(), start - ros::Duration(1.0)));
  ASSERT_TRUE(WaitUntil([&] { return late.Count() >= 1; }, 10.0)) << "the first frame was not answered";
  const ros::WallDuration cloud_delay(std::max(0.1, 3.0 * (late.All().front().second - probe_sent).toSec()));
  std::vector<std::pair<ros::Time, ros::WallTime>> sent;  // stamp, when its cloud went out
  for (int i = 0; i < 20; ++i) {
    const ros::Time stamp = start + ros::Duration(i / 10.0);
    late.image.publish(PhotoImage(TwoTags(), stamp));
    cloud_delay.sleep();
    late.cloud.publish(PhotoCloud(TwoTags(), stamp, 2));
    sent.push_back({stamp, ros::WallTime::now()});
  }
  ASSERT_TRUE(WaitUntil([&] { return late.Count() >= sent.size() + 1; }, 10.0)) << late.Count() - 1 << " of 20 answered";
  int before_cloud = 0;
  const auto all = late.All();
  for (const auto& [stamp, cloud_sent] : sent) {
    const auto it = std::find_if(all.begin(), all.end(), [&](const auto& a) { return a.first->header.stamp == stamp; });
    ASSERT_NE(it, all.end());
    EXPECT_TRUE(MatchesPhoto(*it->first, TwoTags(), true));
    before_cloud += it->second < cloud_sent;
  }
  EXPECT_GE(before_cloud, 10) << "most images must be answered before their cloud exists (clouds "
                               << cloud_delay.toSec() << " s after their image)";
}

// The photo stream with ~output_frame world (a static TF away from the camera) and
// ~tf_from_validated_tracks: one track per marker, validated at its third frame, its filtered pose
// the photo's reference pose moved into world, tighter than one detection's; TF only once validated.
TEST(StampPatterns, ValidatedTracksOnThePhotoStream) {
  Instance instance(*nh, "tracks");
  Collector<TagTracks> tracks(*nh, "/tracks/tracks");
  std::mutex mutex;
  std::map<ros::Time, std::vector<std::string>> tf_children;
  ros::Subscriber tf = nh->subscribe<tf2_msgs::TFMessage>("/tf", 100, [&](const tf2_msgs::TFMessageConstPtr& msg) {
    std::lock_guard<std::mutex> lock(mutex);
    for (const auto& t : msg->transforms) tf_children[t.header.stamp].push_back(t.child_frame_id);
  });
  // world <- camera: 1 m up, 2 m ahead, the optical frame looking along world x.
  const cv::Matx33d world_rotation(0, 0, 1, -1, 0, 0, 0, -1, 0);
  const cv::Vec3d world_translation(2.0, 0.0, 1.0);
  tf2_ros::StaticTransformBroadcaster statics;
  geometry_msgs::TransformStamped world;
  world.header.frame_id = "world";
  world.child_frame_id = kPhotoFrame;
  world.transform.translation.x = world_translation[0];
  world.transform.translation.z = world_translation[2];
  world.transform.rotation.x = world.transform.rotation.z = -0.5;  // the matrix above as a quaternion
  world.transform.rotation.y = world.transform.rotation.w = 0.5;
  statics.sendTransform(world);
  ASSERT_TRUE(instance.Ready());
  const ros::Time start = ros::Time::now();
  instance.info.publish(RaspiInfo(start));
  ros::WallDuration(0.5).sleep();  // the static TF reaches the detector's listener
  const int frames = 6;
  for (int i = 0; i < frames; ++i) {
    const ros::Time stamp = start + ros::Duration(0.1 * (i + 1));
    instance.image.publish(PhotoImage(TwoTags(), stamp));
    const auto msg = tracks.Wait(stamp, 5.0);
    ASSERT_TRUE(msg) << "frame " << i;
    EXPECT_EQ(msg->header.frame_id, "world");
    ASSERT_EQ(msg->tracks.size(), 2u) << "frame " << i;
    const auto tags = instance.tags.Wait(stamp, 5.0);
    ASSERT_TRUE(tags);
    for (const auto& track : msg->tracks) {
      const auto truth = TwoTags().corners.find(track.id);
      ASSERT_NE(truth, TwoTags().corners.end()) << "track of id " << track.id;
      EXPECT_EQ(track.cameras, std::vector<std::string>{kPhotoFrame});
      EXPECT_EQ(track.hits, static_cast<uint32_t>(i + 1));
      EXPECT_EQ(track.misses, 0u);
      EXPECT_EQ(track.validated, i >= 2) << "frame " << i;
      EXPECT_TRUE(track.filtered);
      EXPECT_EQ(track.last_seen, stamp);
      cv::Matx33d rotation;
      cv::Vec3d position;
      ReferencePose(truth->second, rotation, position);
      EXPECT_TRUE(PoseMatches(track.pose.pose, world_rotation * rotation, world_rotation * position + world_translation,
                              cv::norm(position)));
      const auto detection = std::find_if(tags->tags.begin(), tags->tags.end(),
                                          [&](const TagMsg& tag) { return tag.id == track.id; });
      ASSERT_NE(detection, tags->tags.end());
      if (i > 0) {  // the filter holds several frames' worth: below one detection's variance along the view
        EXPECT_LT(track.pose.covariance[0], detection->covariance[0]) << "frame " << i;
      }
    }
  }
  ros::WallDuration(0.3).sleep();
  std::lock_guard<std::mutex> lock(mutex);
  for (int i = 0; i < frames; ++i) {
    const auto& children = tf_children[start + ros::Duration(0.1 * (i + 1))];
    EXPECT_EQ(children.size(), i >= 2 ? 2u : 0u) << "frame " << i << ": TF only from validated tracks";
  }
}

}  // namespace
}  // namespace arucotag::test

int main(int argc, char** argv) {
  testing::InitGoogleTest(&argc, argv);
  ros::init(argc, argv, "test_stamps");
  ros::AsyncSpinner spinner(2);
  spinner.start();
  ros::NodeHandle nh;
  arucotag::test::nh = &nh;
  const int result = RUN_ALL_TESTS();
  spinner.stop();
  return result;
}

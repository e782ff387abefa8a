// Rostest (bad_input.test): malformed input of every kind a driver, a bag or a mistyped launch file
// sends, each to a fresh detector nodelet loaded into one manager (/bad/<case>/detector, topics
// under /bad/<case>). For each: one log message naming the problem (throttled: the bad input is
// sent three times), a count in /diagnostics, then the next good frame detected with the right id
// and pose. The manager must still answer at the end. Under `make sanitize` this is also the
// malformed-input run of the nodelet with ASan and UBSan on.
#include <cmath>
#include <cstring>
#include <functional>
#include <limits>
#include <memory>
#include <random>

#include <diagnostic_msgs/DiagnosticArray.h>
#include <dynamic_reconfigure/Reconfigure.h>
#include <nodelet/NodeletList.h>
#include <nodelet/NodeletLoad.h>
#include <nodelet/NodeletUnload.h>
#include <opencv2/imgcodecs.hpp>
#include <rosgraph_msgs/Log.h>
#include <sensor_msgs/PointField.h>
#include <sensor_msgs/distortion_models.h>
#include <tf2_ros/static_transform_broadcaster.h>

#include "rig.hpp"

namespace arucotag::test {
namespace {

using TagArray = arucotag::ArucoTagArray;
using TagMsg = arucotag::ArucoTag;
using Log = rosgraph_msgs::Log;
using Params = std::vector<std::pair<std::string, XmlRpc::XmlRpcValue>>;

constexpr double kNan = std::numeric_limits<double>::quiet_NaN();
constexpr double kInf = std::numeric_limits<double>::infinity();
constexpr int kRepeats = 3;  // each bad input is sent this often: logged once, counted every time

// What the manager's nodelets logged (they log under the manager's name).
class ManagerLog {
 public:
  explicit ManagerLog(ros::NodeHandle& nh)
      : sub_(nh.subscribe<Log>("/rosout", 500, [this](const rosgraph_msgs::LogConstPtr& log) {
          if (log->name != "/manager") return;
          std::lock_guard<std::mutex> lock(mutex_);
          entries_.push_back(*log);
        })) {}
  void Clear() {
    std::lock_guard<std::mutex> lock(mutex_);
    entries_.clear();
  }
  /// Messages at `min_level` or above that contain `text` ("" for all of them).
  std::vector<std::string> Matching(const std::string& text, uint8_t min_level) const {
    std::lock_guard<std::mutex> lock(mutex_);
    std::vector<std::string> found;
    for (const auto& e : entries_) {
      if (e.level >= min_level && e.msg.find(text) != std::string::npos) found.push_back(e.msg);
    }
    return found;
  }

 private:
  mutable std::mutex mutex_;
  std::vector<Log> entries_;
  ros::Subscriber sub_;
};

// The latest key/values of every diagnostic status, by status name.
class Diagnostics {
 public:
  explicit Diagnostics(ros::NodeHandle& nh)
      : sub_(nh.subscribe<diagnostic_msgs::DiagnosticArray>(
            "/diagnostics", 50, [this](const diagnostic_msgs::DiagnosticArrayConstPtr& msg) {
              std::lock_guard<std::mutex> lock(mutex_);
              for (const auto& status : msg->status) {
                for (const auto& kv : status.values) values_[status.name][kv.key] = kv.value;
              }
            })) {}
  std::string Get(const std::string& status, const std::string& key) const {
    std::lock_guard<std::mutex> lock(mutex_);
    const auto s = values_.find(status);
    if (s == values_.end()) return "";
    const auto v = s->second.find(key);
    return v == s->second.end() ? "" : v->second;
  }
  double Number(const std::string& status, const std::string& key) const {
    const std::string value = Get(status, key);
    return value.empty() ? -1.0 : std::stod(value);
  }

 private:
  mutable std::mutex mutex_;
  std::map<std::string, std::map<std::string, std::string>> values_;
  ros::Subscriber sub_;
};

struct World {
  ros::NodeHandle nh;
  ManagerLog log{nh};
  Diagnostics diagnostics{nh};
  tf2_ros::StaticTransformBroadcaster static_tf;
};
World* world = nullptr;

const Scene& MainScene() {
  static const Scene scene = Render({MainMarker()});
  return scene;
}

// One case: a detector nodelet loaded for it alone, its input publishers and its tags.
class Subject {
 public:
  Subject(const std::string& name, const Params& params) : ns_("/bad/" + name), nh_(world->nh) {
    // Images never wait for a first camera_info, so every frame is answered at once.
    ros::param::set(ns_ + "/detector/camera_info_wait", 0.0);
    ros::param::set(ns_ + "/detector/publish_tf", false);
    for (const auto& [key, value] : params) {
      ros::param::set(ns_ + "/detector/" + key, value);
      if (key == "image_transport") compressed_only_ = std::string(XmlRpc::XmlRpcValue(value)) == "compressed";
      if (key == "use_point_cloud") with_cloud_ = bool(XmlRpc::XmlRpcValue(value));
    }
    image = nh_.advertise<sensor_msgs::Image>(ns_ + "/image", 5);
    compressed = nh_.advertise<sensor_msgs::CompressedImage>(ns_ + "/image/compressed", 5);
    info = nh_.advertise<sensor_msgs::CameraInfo>(ns_ + "/camera_info", 5);
    cloud = nh_.advertise<sensor_msgs::PointCloud2>(ns_ + "/points", 5);
    tags = std::make_unique<Collector<TagArray>>(nh_, ns_ + "/tags");
    nodelet::NodeletLoad load;
    load.request.name = ns_ + "/detector";
    load.request.type = "arucotag/DetectorNodelet";
    loaded_ = ros::service::call("/manager/load_nodelet", load) && load.response.success;
  }
  ~Subject() {
    nodelet::NodeletUnload unload;
    unload.request.name = ns_ + "/detector";
    EXPECT_TRUE(ros::service::call("/manager/unload_nodelet", unload) && unload.response.success)
        << "unloading " << unload.request.name;
    ros::param::del(ns_);
  }

  /// Loaded and subscribed to the inputs this case uses.
  ::testing::AssertionResult Ready() const {
    if (!loaded_) return ::testing::AssertionFailure() << "the manager did not load " << ns_ << "/detector";
    const bool subscribed = WaitUntil(
        [&] {
          return (compressed_only_ ? compressed : image).getNumSubscribers() > 0 && info.getNumSubscribers() > 0 &&
                 (!with_cloud_ || cloud.getNumSubscribers() > 0);
        },
        20.0);
    if (!subscribed) return ::testing::AssertionFailure() << ns_ << "/detector never subscribed its inputs";
    ros::WallDuration(0.2).sleep();  // the manager's other connections to these topics settle
    info.publish(Rig::InfoMessage(MainScene().camera, ros::Time::now()));  // the first image has one
    ros::WallDuration(0.1).sleep();
    return ::testing::AssertionSuccess();
  }

  ros::Time NextStamp() {
    ros::Time stamp = ros::Time::now();
    if (stamp <= last_stamp_) stamp = last_stamp_ + ros::Duration(0, 1000);
    last_stamp_ = stamp;
    return stamp;
  }
  ros::Time last_stamp() const { return last_stamp_; }

  /// One good frame of `scene` (camera_info with the scene's camera, the cloud when the case
  /// uses one, then the image, raw or as a jpeg), with `info_message` instead when given.
  ros::Time PublishGood(const Scene& scene, sensor_msgs::CameraInfoPtr info_message = nullptr) {
    const ros::Time stamp = NextStamp();
    if (!info_message) info_message = Rig::InfoMessage(scene.camera, stamp);
    info_message->header.stamp = stamp;
    info.publish(info_message);
    if (with_cloud_) {
      cloud.publish(Rig::CloudMessage(scene.cloud, stamp, kOpticalFrame));
      CloudHeadStart();
    } else {
      HeadStart();
    }
    PublishImage(scene, stamp);
    return stamp;
  }

  void PublishImage(const Scene& scene, const ros::Time& stamp) {
    if (compressed_only_) {
      sensor_msgs::CompressedImage jpeg;
      jpeg.header.stamp = stamp;
      jpeg.header.frame_id = kOpticalFrame;
      jpeg.format = "bgr8; jpeg compressed bgr8";
      cv::imencode(".jpg", scene.image, jpeg.data, {cv::IMWRITE_JPEG_QUALITY, 95});
      compressed.publish(jpeg);
    } else {
      image.publish(Rig::ImageMessage(scene.image, stamp));
    }
  }

  /// Good frames until one is answered; its tags, or null after `timeout` s.
  boost::shared_ptr<const TagArray> GoodFrame(const Scene& scene = MainScene(),
                                              const sensor_msgs::CameraInfoPtr& info_message = nullptr,
                                              double timeout = 10.0) {
    const ros::WallTime end = ros::WallTime::now() + ros::WallDuration(timeout);
    while (ros::ok() && ros::WallTime::now() < end) {
      const ros::Time stamp = PublishGood(scene, info_message ? boost::make_shared<sensor_msgs::CameraInfo>(*info_message)
                                                              : nullptr);
      if (auto tags_message = tags->Wait(stamp, 1.5)) return tags_message;
    }
    return nullptr;
  }

  /// The nodelet takes the latest camera_info and cloud when an image comes; on separate
  /// connections an image can overtake the camera_info sent just before it.
  static void HeadStart() { ros::WallDuration(0.03).sleep(); }
  /// The same for a cloud (5 MB, deserialised before it is queued, against the image's 0.9 MB):
  /// 30 ms was not always enough on a loaded machine (a clean-clone CI run, the catkin workspace's
  /// run_tests: 'frames whose cloud was rejected' reached 2 of 3 in BadInput.CloudOfFloat64).
  static void CloudHeadStart() { ros::WallDuration(0.2).sleep(); }

  std::string Status() const { return ns_.substr(1) + "/detector: detector"; }
  const std::string& ns() const { return ns_; }

  ros::Publisher image, compressed, info, cloud;
  std::unique_ptr<Collector<TagArray>> tags;

 private:
  std::string ns_;
  ros::NodeHandle nh_;
  bool loaded_ = false, compressed_only_ = false, with_cloud_ = false;
  ros::Time last_stamp_;
};

// The one tag of MainScene with its true pose (in the optical frame unless `to_frame` moves it).
::testing::AssertionResult IsMainTag(const boost::shared_ptr<const TagArray>& msg, uint8_t source,
                                     const Scene& scene = MainScene()) {
  if (!msg) return ::testing::AssertionFailure() << "no tags for a good frame";
  if (msg->tags.size() != 1) return ::testing::AssertionFailure() << msg->tags.size() << " tags, want 1";
  const TagMsg& tag = msg->tags[0];
  if (tag.id != 7) return ::testing::AssertionFailure() << "id " << tag.id << ", want 7";
  if (tag.pose_source != source) {
    return ::testing::AssertionFailure() << "pose source " << int(tag.pose_source) << ", want " << int(source);
  }
  return PoseMatches(tag.pose, scene.markers[0]);
}

struct Report {
  std::string text;                  // distinctive words of the one message about the problem
  uint8_t level = Log::ERROR;        // lowest level it must have
  std::string key;                   // /diagnostics value that counts it
  double count = kRepeats;           // how far the count must get
};

// Sends the bad input kRepeats times (`send` gets a fresh stamp), then expects the report, the
// next good frame answered with the true pose, and no second message about the problem.
void ExpectHandled(Subject& subject, const Report& report, const std::function<void(const ros::Time&)>& send,
                   uint8_t good_source = TagMsg::PNP) {
  world->log.Clear();
  for (int i = 0; i < kRepeats; ++i) {
    send(subject.NextStamp());
    ros::WallDuration(0.05).sleep();
  }
  EXPECT_TRUE(WaitUntil([&] { return !world->log.Matching(report.text, report.level).empty(); }, 10.0))
      << subject.ns() << ": nothing logged containing '" << report.text << "'; logged: "
      << ::testing::PrintToString(world->log.Matching("", Log::DEBUG));
  EXPECT_TRUE(IsMainTag(subject.GoodFrame(), good_source)) << subject.ns() << ": the good frame after the bad input";
  EXPECT_TRUE(WaitUntil([&] { return world->diagnostics.Number(subject.Status(), report.key) >= report.count; },
                        5.0))
      << subject.Status() << " '" << report.key << "' = " << world->diagnostics.Get(subject.Status(), report.key)
      << ", want >= " << report.count;
  EXPECT_EQ(world->log.Matching(report.text, Log::DEBUG).size(), 1u)
      << subject.ns() << ": the problem must be logged once (throttled), got "
      << ::testing::PrintToString(world->log.Matching(report.text, Log::DEBUG));
}

// ---- images ----

const std::string kSkipped = "frames skipped (bad input)";

sensor_msgs::ImagePtr GoodImage(const ros::Time& stamp) { return Rig::ImageMessage(MainScene().image, stamp); }

// Publishes camera_info and the image as a driver would.
std::function<void(const ros::Time&)> SendImage(Subject& s, std::function<void(sensor_msgs::Image&)> spoil) {
  return [&s, spoil](const ros::Time& stamp) {
    s.info.publish(Rig::InfoMessage(MainScene().camera, stamp));
    auto image = GoodImage(stamp);
    spoil(*image);
    s.image.publish(image);
  };
}

TEST(BadInput, ImageStepShorterThanARow) {
  Subject s("wrong_step", {});
  ASSERT_TRUE(s.Ready());
  ASSERT_TRUE(IsMainTag(s.GoodFrame(), TagMsg::PNP));
  ExpectHandled(s, {"step 1919 is shorter than a row of 1920 bytes", Log::ERROR, kSkipped},
                SendImage(s, [](sensor_msgs::Image& image) { image.step -= 1; }));
}

TEST(BadInput, ImageDataShorterThanHeightTimesStep) {
  Subject s("short_data", {});
  ASSERT_TRUE(s.Ready());
  ASSERT_TRUE(IsMainTag(s.GoodFrame(), TagMsg::PNP));
  ExpectHandled(s, {"needs 921600 bytes but the message holds 920000", Log::ERROR, kSkipped},
                SendImage(s, [](sensor_msgs::Image& image) { image.data.resize(920000); }));
}

TEST(BadInput, ImageOfZeroSize) {
  Subject s("zero_size", {});
  ASSERT_TRUE(s.Ready());
  ASSERT_TRUE(IsMainTag(s.GoodFrame(), TagMsg::PNP));
  ExpectHandled(s, {"bgr8 image 0x0 is empty", Log::ERROR, kSkipped}, SendImage(s, [](sensor_msgs::Image& image) {
                  image.width = image.height = image.step = 0;
                  image.data.clear();
                }));
}

TEST(BadInput, ImageClaimingAHugeSizeWithTinyData) {
  Subject s("huge_size", {});
  ASSERT_TRUE(s.Ready());
  ASSERT_TRUE(IsMainTag(s.GoodFrame(), TagMsg::PNP));
  ExpectHandled(s, {"needs 30000000000 bytes but the message holds 64", Log::ERROR, kSkipped},
                SendImage(s, [](sensor_msgs::Image& image) {
                  image.width = image.height = 100000;
                  image.step = 300000;
                  image.data.resize(64);
                }));
}

TEST(BadInput, ImageOfUnknownEncoding) {
  Subject s("unknown_encoding", {});
  ASSERT_TRUE(s.Ready());
  ASSERT_TRUE(IsMainTag(s.GoodFrame(), TagMsg::PNP));
  ExpectHandled(s, {"unsupported image encoding 'bgr10'", Log::ERROR, kSkipped},
                SendImage(s, [](sensor_msgs::Image& image) { image.encoding = "bgr10"; }));
}

TEST(BadInput, GarbageCompressedImage) {
  Subject s("garbage_compressed", {{"image_transport", "compressed"}});
  ASSERT_TRUE(s.Ready());
  ASSERT_TRUE(IsMainTag(s.GoodFrame(), TagMsg::PNP));
  std::mt19937 random(7);
  ExpectHandled(s, {"neither jpeg nor png data", Log::ERROR, kSkipped}, [&](const ros::Time& stamp) {
    s.info.publish(Rig::InfoMessage(MainScene().camera, stamp));
    sensor_msgs::CompressedImage garbage;
    garbage.header.stamp = stamp;
    garbage.header.frame_id = kOpticalFrame;
    garbage.format = "bgr8; jpeg compressed bgr8";
    garbage.data.resize(5000);
    for (auto& byte : garbage.data) byte = static_cast<uint8_t>(random());
    garbage.data[0] = 0x42;  // never a jpeg's ff d8 by chance
    s.compressed.publish(garbage);
  });
}

TEST(BadInput, CompressedImageClaimingAHugeSize) {
  Subject s("huge_jpeg", {{"image_transport", "compressed"}});
  ASSERT_TRUE(s.Ready());
  ASSERT_TRUE(IsMainTag(s.GoodFrame(), TagMsg::PNP));
  ExpectHandled(s, {"claims a 60000x50000 image", Log::ERROR, kSkipped}, [&](const ros::Time& stamp) {
    s.info.publish(Rig::InfoMessage(MainScene().camera, stamp));
    sensor_msgs::CompressedImage jpeg;
    jpeg.header.stamp = stamp;
    jpeg.header.frame_id = kOpticalFrame;
    jpeg.format = "bgr8; jpeg compressed bgr8";
    // Start of image, then a baseline frame header: 8 bits, 50000 rows, 60000 columns, 3 components.
    jpeg.data = {0xff, 0xd8, 0xff, 0xc0, 0x00, 0x11, 0x08, 0xc3, 0x50, 0xea, 0x60, 0x03,
                 0x01, 0x11, 0x00, 0x02, 0x11, 0x01, 0x03, 0x11, 0x01, 0xff, 0xd9};
    s.compressed.publish(jpeg);
  });
}

TEST(BadInput, ImageWithoutFrameId) {
  Subject s("no_frame_id", {{"publish_tf", true}});
  ASSERT_TRUE(s.Ready());
  ASSERT_TRUE(IsMainTag(s.GoodFrame(), TagMsg::PNP));
  ExpectHandled(s, {"no frame_id", Log::ERROR, "frames without frame_id"},
                SendImage(s, [](sensor_msgs::Image& image) { image.header.frame_id.clear(); }));
}

TEST(BadInput, ImageStampsGoingBack) {
  Subject s("stamps_back", {});
  ASSERT_TRUE(s.Ready());
  ASSERT_TRUE(IsMainTag(s.GoodFrame(), TagMsg::PNP));
  const ros::Time start = s.last_stamp();
  int back = 0;
  ExpectHandled(s, {"image stamps went back", Log::WARN, "stamps going back (loops)"}, [&](const ros::Time&) {
    const ros::Time stamp = start - ros::Duration(10.0 * ++back);
    SendImage(s, [](sensor_msgs::Image&) {})(stamp);
  });
}

TEST(BadInput, ImageStampsRepeating) {
  Subject s("stamps_repeat", {});
  ASSERT_TRUE(s.Ready());
  ASSERT_TRUE(IsMainTag(s.GoodFrame(), TagMsg::PNP));
  const ros::Time repeated = s.last_stamp();
  ExpectHandled(s, {"repeats the previous image's", Log::WARN, "repeated stamps"},
                [&](const ros::Time&) { SendImage(s, [](sensor_msgs::Image&) {})(repeated); });
}

// ---- camera_info ----

const std::string kNoInfo = "frames without camera_info";

std::function<void(const ros::Time&)> SendInfo(Subject& s, std::function<void(sensor_msgs::CameraInfo&)> spoil) {
  return [&s, spoil](const ros::Time& stamp) {
    auto info = Rig::InfoMessage(MainScene().camera, stamp);
    spoil(*info);
    s.info.publish(info);
    Subject::HeadStart();
    s.image.publish(GoodImage(stamp));
  };
}

// A camera_info the nodelet cannot use: named once, frames keep ids and corners without a pose.
void ExpectInfoRejected(const std::string& name, const std::string& text,
                        std::function<void(sensor_msgs::CameraInfo&)> spoil, const Params& params = {}) {
  Subject s(name, params);
  ASSERT_TRUE(s.Ready());
  ASSERT_TRUE(IsMainTag(s.GoodFrame(), TagMsg::PNP));
  std::vector<ros::Time> stamps;
  ExpectHandled(s, {text, Log::ERROR, kNoInfo}, [&](const ros::Time& stamp) {
    stamps.push_back(stamp);
    SendInfo(s, spoil)(stamp);
  });
  for (const auto& stamp : stamps) {
    const auto msg = s.tags->Wait(stamp, 2.0);
    ASSERT_TRUE(msg) << "a frame with a bad camera_info still gets ids and corners";
    ASSERT_EQ(msg->tags.size(), 1u);
    EXPECT_EQ(msg->tags[0].id, 7);
    EXPECT_EQ(msg->tags[0].pose_source, TagMsg::NONE) << "no pose from a camera_info that was refused";
  }
}

TEST(BadInput, CameraInfoKAllZero) {
  ExpectInfoRejected("k_zero", "camera_info K is all zero", [](sensor_msgs::CameraInfo& info) { info.K.fill(0.0); });
}

TEST(BadInput, CameraInfoKNan) {
  ExpectInfoRejected("k_nan", "camera_info K has a NaN or infinite entry",
                     [](sensor_msgs::CameraInfo& info) { info.K[0] = kNan; });
}

TEST(BadInput, CameraInfoKInfinite) {
  ExpectInfoRejected("k_inf", "camera_info K has a NaN or infinite entry",
                     [](sensor_msgs::CameraInfo& info) { info.K[5] = kInf; });
}

TEST(BadInput, CameraInfoDistortionOfSixCoefficients) {
  ExpectInfoRejected("d_6", "camera distortion has 6 coefficients; OpenCV accepts 4, 5, 8, 12 or 14",
                     [](sensor_msgs::CameraInfo& info) { info.D = {-0.1, 0.02, 0.001, 0.0, 0.001, 0.01}; });
}

TEST(BadInput, CameraInfoDistortionOfThreeCoefficients) {
  ExpectInfoRejected("d_3", "camera distortion has 3 coefficients",
                     [](sensor_msgs::CameraInfo& info) { info.D = {-0.1, 0.02, 0.001}; });
}

TEST(BadInput, CameraInfoUnknownDistortionModel) {
  ExpectInfoRejected("unknown_model", "distortion model 'magic_lens' is not supported", [](sensor_msgs::CameraInfo& info) {
    info.distortion_model = "magic_lens";
    info.D = {-0.1, 0.02, 0.001, 0.0, 0.001};
  });
}

TEST(BadInput, CameraInfoPAllZeroWhenRectified) {
  ExpectInfoRejected("p_zero", "camera_info P is all zero", [](sensor_msgs::CameraInfo& info) { info.P.fill(0.0); },
                     {{"rectified", true}});
}

TEST(BadInput, CameraInfoForAnotherImageSize) {
  ExpectInfoRejected("info_size", "camera_info is for a 1280x960 image", [](sensor_msgs::CameraInfo& info) {
    info.width = 1280;
    info.height = 960;
  });
}

// Every length OpenCV's pinhole model reads (none, k1 k2 p1 p2, + k3, + k4..k6, + s1..s4, + tau x y):
// a frame rendered through that lens gives the true pose, without a word in the log.
TEST(BadInput, EveryDistortionLengthOpenCvAcceptsGivesTruePoses) {
  Subject s("d_lengths", {});
  ASSERT_TRUE(s.Ready());
  const std::vector<double> all = {-0.12, 0.04,   0.001, -0.0008, -0.01, 0.015, 0.003,
                                   0.002, 0.0015, -0.001, 0.001,  0.0005, 0.003, -0.002};
  world->log.Clear();
  for (const size_t n : {0, 4, 5, 8, 12, 14}) {
    Scene scene;
    scene.camera = TestCamera();
    scene.camera.dist.assign(all.begin(), all.begin() + n);
    scene.markers = {MainMarker()};
    scene.image = sim::RenderScene(scene.camera, scene.markers, {});
    auto info = Rig::InfoMessage(scene.camera, ros::Time());
    info->D = scene.camera.dist;
    info->distortion_model = n <= 5 ? sensor_msgs::distortion_models::PLUMB_BOB
                                    : sensor_msgs::distortion_models::RATIONAL_POLYNOMIAL;
    EXPECT_TRUE(IsMainTag(s.GoodFrame(scene, info), TagMsg::PNP, scene)) << n << " coefficients";
  }
  EXPECT_TRUE(world->log.Matching("", Log::WARN).empty())
      << ::testing::PrintToString(world->log.Matching("", Log::WARN));
}

// ---- point clouds ----

const std::string kCloudRejected = "frames whose cloud was rejected (bad input)";

sensor_msgs::PointCloud2Ptr GoodCloud(const ros::Time& stamp) {
  return Rig::CloudMessage(MainScene().cloud, stamp, kOpticalFrame);
}

std::function<void(const ros::Time&)> SendCloud(Subject& s, std::function<void(sensor_msgs::PointCloud2&)> spoil) {
  return [&s, spoil](const ros::Time& stamp) {
    s.info.publish(Rig::InfoMessage(MainScene().camera, stamp));
    auto cloud = GoodCloud(stamp);
    spoil(*cloud);
    s.cloud.publish(cloud);
    Subject::CloudHeadStart();
    s.image.publish(GoodImage(stamp));
  };
}

// A cloud the nodelet cannot use: named once, counted, PnP alone meanwhile; the next good cloud fuses.
void ExpectCloudRejected(const std::string& name, const Report& report,
                         std::function<void(sensor_msgs::PointCloud2&)> spoil) {
  Subject s(name, {{"use_point_cloud", true}});
  ASSERT_TRUE(s.Ready());
  ASSERT_TRUE(IsMainTag(s.GoodFrame(), TagMsg::FUSED));
  std::vector<ros::Time> stamps;
  ExpectHandled(
      s, report,
      [&](const ros::Time& stamp) {
        stamps.push_back(stamp);
        SendCloud(s, spoil)(stamp);
      },
      TagMsg::FUSED);
  for (const auto& stamp : stamps) {
    EXPECT_TRUE(IsMainTag(s.tags->Wait(stamp, 2.0), TagMsg::PNP)) << "PnP alone beside a bad cloud";
  }
}

TEST(BadInput, CloudUnorganized) {
  ExpectCloudRejected("cloud_unorganized", {"point cloud is not organized (307200x1)", Log::ERROR, kCloudRejected},
                      [](sensor_msgs::PointCloud2& cloud) {
                        cloud.width *= cloud.height;
                        cloud.height = 1;
                        cloud.row_step = cloud.width * cloud.point_step;
                      });
}

TEST(BadInput, CloudOfAnotherSize) {
  ExpectCloudRejected("cloud_size", {"point cloud is 500x300 but the image is 640x480", Log::ERROR, kCloudRejected},
                      [](sensor_msgs::PointCloud2& cloud) {
                        cloud.width = 500;
                        cloud.height = 300;
                        cloud.row_step = cloud.width * cloud.point_step;
                        cloud.data.resize(size_t{cloud.row_step} * cloud.height);
                      });
}

void FillXyz(sensor_msgs::PointCloud2& cloud, float value) {
  for (size_t at = 0; at + cloud.point_step <= cloud.data.size(); at += cloud.point_step) {
    for (int axis = 0; axis < 3; ++axis) std::memcpy(&cloud.data[at + 4 * axis], &value, sizeof(value));
  }
}

TEST(BadInput, CloudAllNan) {
  ExpectCloudRejected("cloud_nan", {"too few finite points on every tag", Log::WARN, "frames whose cloud has no depth on any tag"},
                      [](sensor_msgs::PointCloud2& cloud) { FillXyz(cloud, std::numeric_limits<float>::quiet_NaN()); });
}

TEST(BadInput, CloudAllInfinite) {
  ExpectCloudRejected("cloud_inf", {"too few finite points on every tag", Log::WARN, "frames whose cloud has no depth on any tag"},
                      [](sensor_msgs::PointCloud2& cloud) { FillXyz(cloud, std::numeric_limits<float>::infinity()); });
}

TEST(BadInput, CloudWithoutX) {
  ExpectCloudRejected("cloud_no_x", {"point cloud has no 'x' field", Log::ERROR, kCloudRejected},
                      [](sensor_msgs::PointCloud2& cloud) { cloud.fields.erase(cloud.fields.begin()); });
}

TEST(BadInput, CloudOfFloat64) {
  ExpectCloudRejected("cloud_float64", {"point cloud field 'x' is not a single float32", Log::ERROR, kCloudRejected},
                      [](sensor_msgs::PointCloud2& cloud) {
                        for (int axis = 0; axis < 3; ++axis) {
                          cloud.fields[axis].datatype = sensor_msgs::PointField::FLOAT64;
                          cloud.fields[axis].offset = 8 * axis;
                        }
                        cloud.fields.resize(3);
                        cloud.point_step = 24;
                        cloud.row_step = cloud.width * cloud.point_step;
                        cloud.data.assign(size_t{cloud.row_step} * cloud.height, 0);
                      });
}

TEST(BadInput, CloudPointStepShorterThanItsFields) {
  ExpectCloudRejected("cloud_point_step", {"point cloud field 'z' lies beyond point_step", Log::ERROR, kCloudRejected},
                      [](sensor_msgs::PointCloud2& cloud) {
                        cloud.point_step = 11;
                        cloud.row_step = cloud.width * cloud.point_step;
                      });
}

// One padding byte, then x y z (point_step 13): the floats sit at odd addresses. A legal
// PointCloud2: read like any other, fused poses, nothing logged.
TEST(BadInput, CloudWithOddPointStepIsRead) {
  Subject s("cloud_odd_step", {{"use_point_cloud", true}});
  ASSERT_TRUE(s.Ready());
  world->log.Clear();
  const ros::Time stamp = s.NextStamp();
  const auto good = GoodCloud(stamp);
  auto packed = boost::make_shared<sensor_msgs::PointCloud2>(*good);
  packed->fields.resize(3);
  for (auto& field : packed->fields) field.offset += 1;
  packed->point_step = 13;
  packed->row_step = packed->width * packed->point_step;
  packed->data.assign(size_t{packed->row_step} * packed->height, 0);
  for (size_t i = 0; i < size_t{packed->width} * packed->height; ++i) {
    std::memcpy(&packed->data[i * 13 + 1], &good->data[i * 16], 12);
  }
  s.info.publish(Rig::InfoMessage(MainScene().camera, stamp));
  s.cloud.publish(packed);
  Subject::CloudHeadStart();
  s.image.publish(GoodImage(stamp));
  EXPECT_TRUE(IsMainTag(s.tags->Wait(stamp, 5.0), TagMsg::FUSED));
  EXPECT_TRUE(world->log.Matching("", Log::WARN).empty())
      << ::testing::PrintToString(world->log.Matching("", Log::WARN));
}

// ---- other ----

dynamic_reconfigure::Config Reconfigure(const std::string& service, const std::string& name, int value) {
  dynamic_reconfigure::Reconfigure srv;
  dynamic_reconfigure::IntParameter p;
  p.name = name;
  p.value = value;
  srv.request.config.ints.push_back(p);
  EXPECT_TRUE(ros::service::call(service, srv)) << service;
  return srv.response.config;
}

int IntValue(const dynamic_reconfigure::Config& config, const std::string& name) {
  for (const auto& p : config.ints) {
    if (p.name == name) return p.value;
  }
  return -1;
}

// dynamic_reconfigure clamps a value to the cfg range before the nodelet sees it: 150 becomes the
// window minimum's 99, which is above the maximum 23, so the nodelet refuses the change, names it
// and keeps detecting with the previous settings.
TEST(BadInput, ReconfigureOutOfRange) {
  Subject s("reconfigure", {});
  ASSERT_TRUE(s.Ready());
  ASSERT_TRUE(IsMainTag(s.GoodFrame(), TagMsg::PNP));
  const std::string service = s.ns() + "/detector/set_parameters";
  world->log.Clear();
  const auto config = Reconfigure(service, "adaptive_thresh_win_size_min", 150);
  EXPECT_EQ(IntValue(config, "adaptive_thresh_win_size_min"), 3) << "the value in use, not the refused one";
  EXPECT_TRUE(WaitUntil([&] { return !world->log.Matching("dynamic_reconfigure rejected", Log::ERROR).empty(); }, 5.0));
  EXPECT_TRUE(IsMainTag(s.GoodFrame(), TagMsg::PNP));
  EXPECT_TRUE(WaitUntil([&] { return world->diagnostics.Number(s.Status(), "reconfigure requests rejected") == 1; },
                        5.0));
  EXPECT_NE(world->diagnostics.Get(s.Status(), "last error").find("dynamic_reconfigure rejected"), std::string::npos)
      << world->diagnostics.Get(s.Status(), "last error");
  // Within the cfg's range but out of the server's: clamped, applied, and the response says so.
  EXPECT_EQ(IntValue(Reconfigure(service, "corner_refinement_win_size", 500), "corner_refinement_win_size"), 30);
  EXPECT_TRUE(IsMainTag(s.GoodFrame(), TagMsg::PNP));
}

// ~output_frame with no transform yet: frames are dropped (never sent in the optical frame),
// named and counted; once the transform comes, poses go out in output_frame.
TEST(BadInput, OutputFrameWithoutTransform) {
  Subject s("no_tf", {{"output_frame", "bad_input_base"}, {"queue_size", 2}});
  ASSERT_TRUE(s.Ready());
  world->log.Clear();
  std::vector<ros::Time> stamps;
  for (int i = 0; i < 6; ++i) {
    stamps.push_back(s.PublishGood(MainScene()));
    ros::WallDuration(0.05).sleep();
  }
  EXPECT_TRUE(WaitUntil([&] { return !world->log.Matching("bad_input_base", Log::WARN).empty(); }, 10.0))
      << ::testing::PrintToString(world->log.Matching("", Log::DEBUG));
  EXPECT_TRUE(WaitUntil(
      [&] { return world->diagnostics.Number(s.Status(), "frames dropped (no output_frame transform)") >= 1; }, 5.0));

  geometry_msgs::TransformStamped tf;
  tf.header.frame_id = "bad_input_base";
  tf.child_frame_id = kOpticalFrame;
  tf.transform.translation.x = 0.5;
  tf.transform.translation.y = -0.2;
  tf.transform.translation.z = 1.0;
  tf.transform.rotation.w = 1.0;
  world->static_tf.sendTransform(tf);
  const auto msg = s.GoodFrame();
  ASSERT_TRUE(msg);
  for (const auto& stamp : stamps) {
    const auto early = s.tags->First(stamp);
    EXPECT_TRUE(!early || early->header.frame_id == "bad_input_base") << "a frame went out in the optical frame";
  }
  EXPECT_EQ(msg->header.frame_id, "bad_input_base");
  ASSERT_EQ(msg->tags.size(), 1u);
  EXPECT_EQ(msg->tags[0].id, 7);
  const sim::Marker truth = MainMarker();
  EXPECT_TRUE(PoseMatches(msg->tags[0].pose, Rotation(truth), truth.tvec + cv::Vec3d(0.5, -0.2, 1.0),
                          cv::norm(truth.tvec)));
  EXPECT_EQ(world->log.Matching("bad_input_base", Log::WARN).size(), 1u)
      << ::testing::PrintToString(world->log.Matching("bad_input_base", Log::WARN));
}

// Last: after all of the above the manager still runs and holds none of the cases' nodelets.
TEST(BadInput, ZzManagerStillAnswers) {
  nodelet::NodeletList list;
  ASSERT_TRUE(ros::service::call("/manager/list", list)) << "the manager died";
  for (const auto& name : list.response.nodelets) {
    EXPECT_EQ(name.rfind("/bad/", 0), std::string::npos) << name << " was not unloaded";
  }
}

}  // namespace
}  // namespace arucotag::test

int main(int argc, char** argv) {
  testing::InitGoogleTest(&argc, argv);
  ros::init(argc, argv, "test_bad_input");
  ros::AsyncSpinner spinner(2);
  spinner.start();
  {
    arucotag::test::World world;
    arucotag::test::world = &world;
    ros::WallDuration(0.5).sleep();  // /rosout and /diagnostics connect before the first case
    const int result = RUN_ALL_TESTS();
    arucotag::test::world = nullptr;
    spinner.stop();
    return result;
  }
}

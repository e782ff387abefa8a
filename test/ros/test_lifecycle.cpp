// Rostest (lifecycle.test): loading the detector nodelet with bad parameters and unloading and
// reloading it 20 times, all in one manager that must keep answering throughout.
#include <algorithm>

#include <diagnostic_msgs/DiagnosticArray.h>
#include <nodelet/NodeletList.h>
#include <nodelet/NodeletLoad.h>
#include <nodelet/NodeletUnload.h>
#include <rosgraph_msgs/Log.h>

#include "rig.hpp"

namespace arucotag::test {
namespace {

bool Load(const std::string& name) {
  nodelet::NodeletLoad load;
  load.request.name = name;
  load.request.type = "arucotag/DetectorNodelet";
  const std::string ns = name.substr(0, name.rfind('/'));
  for (const char* topic : {"image", "camera_info"}) {
    load.request.remap_source_args.push_back(ns + "/" + topic);
    load.request.remap_target_args.push_back(std::string("/cam/") + topic);
  }
  return ros::service::call("/manager/load_nodelet", load) && load.response.success;
}

bool Unload(const std::string& name) {
  nodelet::NodeletUnload unload;
  unload.request.name = name;
  return ros::service::call("/manager/unload_nodelet", unload) && unload.response.success;
}

std::vector<std::string> Loaded() {
  nodelet::NodeletList list;
  if (!ros::service::call("/manager/list", list)) return {"<manager did not answer>"};
  return list.response.nodelets;
}

// Errors the manager logged, in order.
class ErrorLog {
 public:
  explicit ErrorLog(ros::NodeHandle& nh)
      : sub_(nh.subscribe<rosgraph_msgs::Log>("/rosout", 100, [this](const rosgraph_msgs::LogConstPtr& log) {
          if (log->level < rosgraph_msgs::Log::ERROR || log->name != "/manager") return;
          std::lock_guard<std::mutex> lock(mutex_);
          errors_.push_back(log->msg);
        })) {}
  bool WaitFor(const std::string& text, double timeout) {
    return WaitUntil(
        [&] {
          std::lock_guard<std::mutex> lock(mutex_);
          return std::any_of(errors_.begin(), errors_.end(),
                             [&](const std::string& e) { return e.find(text) != std::string::npos; });
        },
        timeout);
  }

 private:
  std::mutex mutex_;
  std::vector<std::string> errors_;
  ros::Subscriber sub_;
};

TEST(Lifecycle, BadParametersAreNamedAndLeaveTheManagerAlive) {
  ros::NodeHandle nh;
  ErrorLog errors(nh);
  Rig rig(nh);
  std::mutex mutex;
  std::map<std::string, diagnostic_msgs::DiagnosticStatus> statuses;
  auto diagnostics = nh.subscribe<diagnostic_msgs::DiagnosticArray>(
      "/diagnostics", 20, [&](const diagnostic_msgs::DiagnosticArrayConstPtr& msg) {
        std::lock_guard<std::mutex> lock(mutex);
        for (const auto& status : msg->status) statuses[status.name] = status;
      });
  ros::WallDuration(0.5).sleep();  // let /rosout connect before the first error is logged

  const std::vector<std::pair<std::string, std::string>> cases = {
      {"/bad_dictionary/detector", "~dictionary"},  {"/bad_size/detector", "~tag_size must be > 0"},
      {"/bad_sizes/detector", "~tag_sizes"},        {"/bad_source/detector", "~pose_source"},
      {"/bad_type/detector", "~queue_size must be an integer"},
      {"/bad_windows/detector", "adaptive_thresh_win_size_max"},
      {"/bad_bundles/detector", "~bundles: bundle 'post_b' member id 4: id 4 is also in bundle 'post_a'"},
      {"/bad_bundle_size/detector", "~bundles: bundle 'post_a' member id 4: size must be > 0 m"},
      {"/bad_corner_noise/detector", "~corner_noise must be >= 0 px"},
  };
  for (const auto& [name, message] : cases) {
    SCOPED_TRACE(name);
    EXPECT_TRUE(Load(name)) << "a bad parameter must not fail the load (nor kill the manager)";
    EXPECT_TRUE(errors.WaitFor(message, 5.0)) << "expected an error naming " << message;
  }
  ros::WallDuration(0.5).sleep();
  EXPECT_EQ(rig.image_pub().getNumSubscribers(), 0u) << "inert nodelets subscribe to nothing";

  const bool reported = WaitUntil(
      [&] {
        std::lock_guard<std::mutex> lock(mutex);
        const auto it = statuses.find("bad_dictionary/detector: detector");
        return it != statuses.end() && it->second.level == diagnostic_msgs::DiagnosticStatus::ERROR &&
               it->second.message.find("inert") != std::string::npos;
      },
      5.0);
  EXPECT_TRUE(reported) << "diagnostics must report the inert nodelet as ERROR";

  const auto loaded = Loaded();
  for (const auto& [name, message] : cases) {
    EXPECT_NE(std::find(loaded.begin(), loaded.end(), name), loaded.end()) << name;
    EXPECT_TRUE(Unload(name)) << name;
  }
  EXPECT_TRUE(Loaded().empty());
}

TEST(Lifecycle, UnloadAndReloadTwentyTimes) {
  ros::NodeHandle nh;
  Rig rig(nh);
  Collector<arucotag::ArucoTagArray> tags(nh, "/reload/tags");
  const Scene scene = Render({MainMarker()});
  for (int cycle = 0; cycle < 20; ++cycle) {
    SCOPED_TRACE("cycle " + std::to_string(cycle));
    ASSERT_TRUE(Load("/reload/detector"));
    const auto msg = rig.PublishUntil(scene, tags);
    ASSERT_TRUE(msg) << "the reloaded nodelet did not answer";
    ASSERT_EQ(msg->tags.size(), 1u);
    EXPECT_EQ(msg->tags[0].id, 7);
    EXPECT_TRUE(PoseMatches(msg->tags[0].pose, scene.markers[0]));
    // Unload with frames still in flight.
    rig.Publish(scene);
    rig.Publish(scene);
    ASSERT_TRUE(Unload("/reload/detector"));
    ASSERT_TRUE(Loaded().empty()) << "the manager must answer and hold nothing after unload";
  }
}

}  // namespace
}  // namespace arucotag::test

int main(int argc, char** argv) {
  testing::InitGoogleTest(&argc, argv);
  ros::init(argc, argv, "test_lifecycle");
  ros::AsyncSpinner spinner(2);
  spinner.start();
  if (!ros::service::waitForService("/manager/load_nodelet", 30000)) {
    ROS_ERROR("no nodelet manager; the tests will fail");
  }
  const int result = RUN_ALL_TESTS();
  spinner.stop();
  return result;
}

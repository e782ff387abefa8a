// soak: `make soak` (scripts/soak.sh starts a master and a nodelet manager, then this). Two phases
// against the real manager process, each with a budget it fails past:
//   1. SOAK_SECONDS (default 600) of 1280x720 frames of a real photo, camera_info and an organized
//      cloud at 30 Hz into arucotag/DetectorNodelet: manager RSS growth after the first minute
//      (< 1 MB; RSS at rest, see RestRssMb), frames answered out of frames sent (100 % while the mean
//      processing time is below the frame period), latency publish -> tags (median, p99), manager CPU
//      per frame.
//   2. 100 load/unload cycles of the nodelet in the same manager with a tags subscriber attached and
//      frames flowing: every cycle publishes again, the manager survives and its RSS at rest grows
//      < 2 MB from cycle 10 to the end.
//
//   soak --manager /soak_manager --manager-pid PID --photo test/data/.../tag_245-246_d7_14cm.png
//        [--seconds 600] [--cycles 100]
#include <arucotag/ros/messages.hpp>  // first: renames the generated ArucoTag message

#include <algorithm>
#include <atomic>
#include <chrono>
#include <cstdio>
#include <fstream>
#include <functional>
#include <limits>
#include <map>
#include <mutex>
#include <sstream>
#include <string>
#include <thread>
#include <vector>

#include <boost/make_shared.hpp>
#include <diagnostic_msgs/DiagnosticArray.h>
#include <nodelet/NodeletList.h>
#include <nodelet/NodeletLoad.h>
#include <nodelet/NodeletUnload.h>
#include <opencv2/imgcodecs.hpp>
#include <ros/ros.h>
#include <sensor_msgs/CameraInfo.h>
#include <sensor_msgs/Image.h>
#include <sensor_msgs/PointCloud2.h>
#include <sensor_msgs/PointField.h>

#include <arucotag/arucotag.hpp>
#include <arucotag/sim.hpp>

namespace arucotag::soak {
namespace {

using Clock = std::chrono::steady_clock;
constexpr double kFrameRate = 30.0;
constexpr const char* kNamespace = "/soak";
constexpr const char* kFrame = "soak_optical";
constexpr double kStatsWindow = 100;  // frames behind the nodelet's diagnostics means
constexpr const char* kProcessingMean = "processing time mean (ms)";

struct Options {
  std::string manager = "/soak_manager";
  int manager_pid = 0;
  std::string photo;
  double seconds = 600.0;
  int cycles = 100;
};

Options Parse(int argc, char** argv) {
  Options o;
  for (int i = 1; i < argc; ++i) {
    const std::string arg = argv[i];
    if (i + 1 >= argc) throw Error("missing value after " + arg);
    const std::string value = argv[++i];
    if (arg == "--manager") {
      o.manager = value;
    } else if (arg == "--manager-pid") {
      o.manager_pid = std::stoi(value);
    } else if (arg == "--photo") {
      o.photo = value;
    } else if (arg == "--seconds") {
      o.seconds = std::stod(value);
    } else if (arg == "--cycles") {
      o.cycles = std::stoi(value);
    } else {
      throw Error("unknown option " + arg);
    }
  }
  if (o.manager_pid <= 0 || o.photo.empty()) throw Error("--manager-pid and --photo are required");
  return o;
}

// The manager's resident set (MB) and CPU time (s), from /proc.
double RssMb(int pid) {
  std::ifstream status("/proc/" + std::to_string(pid) + "/status");
  std::string line;
  while (std::getline(status, line)) {
    if (line.rfind("VmRSS:", 0) == 0) return std::stod(line.substr(6)) / 1024.0;
  }
  throw Error("manager process " + std::to_string(pid) + " is gone");
}

double CpuSeconds(int pid) {
  std::ifstream stat("/proc/" + std::to_string(pid) + "/stat");
  std::string text((std::istreambuf_iterator<char>(stat)), std::istreambuf_iterator<char>());
  std::istringstream fields(text.substr(text.rfind(')') + 2));  // after "pid (name) "
  std::vector<std::string> f{std::istream_iterator<std::string>(fields), {}};
  if (f.size() < 13) throw Error("cannot read /proc/" + std::to_string(pid) + "/stat");
  return (std::stod(f[11]) + std::stod(f[12])) / static_cast<double>(sysconf(_SC_CLK_TCK));  // utime + stime
}

double Percentile(std::vector<double> v, double q);

// The manager's RSS at rest: frames stopped, every frame sent answered (or none for 1 s), then two
// of the nodelet's trims (malloc_trim once a second) later, the lowest of 20 samples 100 ms apart.
// While frames flow, RSS is a sawtooth: each trim drops it by the arena pages freed since the last,
// and it climbs again by 40-80 MB before the next as 15 MB clouds and receive buffers are freed and
// allocated elsewhere, with 0-14 clouds in flight on top. A lowest sample once a second then depends
// on where the samples fall against the trims: one 150 s run, sampled at ten phases, gave growths from
// -37 to +15 MB while glibc's heap in use (mallinfo2) had the same lowest value in both windows to
// 0.05 MB. At rest the heap in use is what the nodelet keeps (its ~cloud_cache_size clouds, its
// buffers): the same to 0.03 MB at both ends of a run. RSS at rest can still differ by what glibc
// leaves resident at the top of its thread arenas, which malloc_trim does not trim (README, Reliability).
struct RestRss {
  double mb = 0.0, spread = 0.0;  // lowest sample, and highest minus lowest
};

RestRss RestRssMb(int pid, const std::function<size_t()>& answered, size_t sent) {
  const auto quiet_since = [&] {
    size_t last = answered();
    auto since = Clock::now();
    const auto end = Clock::now() + std::chrono::seconds(20);
    while (Clock::now() < end && last < sent && Clock::now() - since < std::chrono::seconds(1)) {
      std::this_thread::sleep_for(std::chrono::milliseconds(50));
      const size_t now = answered();
      if (now != last) since = Clock::now();
      last = now;
    }
  };
  quiet_since();
  std::this_thread::sleep_for(std::chrono::milliseconds(2500));
  std::vector<double> samples;
  for (int i = 0; i < 20; ++i) {
    samples.push_back(RssMb(pid));
    std::this_thread::sleep_for(std::chrono::milliseconds(100));
  }
  const auto [lo, hi] = std::minmax_element(samples.begin(), samples.end());
  return {*lo, *hi - *lo};
}

double Percentile(std::vector<double> v, double q) {
  if (v.empty()) return 0.0;
  std::sort(v.begin(), v.end());
  return v[static_cast<size_t>(q * (v.size() - 1) + 0.5)];
}

// One 1280x720 frame of the real photo (its marker rows), its camera_info and an organized cloud
// that agrees with the poses the core finds on it: what a stereo camera would send.
struct Frame {
  sensor_msgs::Image image;
  sensor_msgs::CameraInfo info;
  sensor_msgs::PointCloud2 cloud;
};

Frame MakeFrame(const std::string& path) {
  const cv::Mat photo = cv::imread(path);
  if (photo.rows < 720 || photo.cols != 1280) throw Error("need a 1280 px wide photo of >= 720 rows: " + path);
  const int top = 100;  // the fiducials photos' markers lie in rows 150-410
  const cv::Mat bgr = photo.rowRange(top, top + 720).clone();
  // UbiquityRobotics/fiducials' calibration of that camera, principal point moved with the crop.
  const cv::Matx33d K(1006.126285753055, 0, 655.8639244150409, 0, 1004.015433012594, 490.6140221242933 - top, 0, 0,
                      1);
  const std::vector<double> D{0.1349735087283542, -0.2335869827451621, 0.0006697030315075139, 0.004846737465872353,
                              0.0};
  Frame f;
  f.image.header.frame_id = f.info.header.frame_id = f.cloud.header.frame_id = kFrame;
  f.image.width = f.info.width = bgr.cols;
  f.image.height = f.info.height = bgr.rows;
  f.image.encoding = "bgr8";
  f.image.step = bgr.cols * 3;
  f.image.data.assign(bgr.data, bgr.data + bgr.total() * 3);
  f.info.distortion_model = "plumb_bob";
  f.info.D = D;
  for (int i = 0; i < 9; ++i) f.info.K[i] = K.val[i];
  f.info.R = {1, 0, 0, 0, 1, 0, 0, 0, 1};
  for (int r = 0; r < 3; ++r)
    for (int c = 0; c < 3; ++c) f.info.P[r * 4 + c] = K(r, c);

  DetectorConfig config;
  config.dictionary = "DICT_5X5_1000";
  config.default_side_length = 0.145;
  cv::Mat grey;
  PreprocessFrame(bgr, grey);
  std::vector<ArucoTag> tags = Detect(grey, Detector(config));
  const CameraModel camera = CameraModel::FromIntrinsics(K, D);
  for (auto& tag : tags) EstimatePoseFromPNP(camera, tag);
  if (tags.size() != 2) throw Error("expected the photo's two markers, found " + std::to_string(tags.size()));

  std::vector<sim::Marker> markers;
  for (const auto& tag : tags) markers.push_back({tag.id, tag.side_length, tag.rvec, tag.tvec});
  const cv::Mat points = sim::MarkerPlanesCloud(K, D, bgr.size(), 1, markers, 1.5);  // a wall behind them
  f.cloud.height = bgr.rows;
  f.cloud.width = bgr.cols;
  const char* names[] = {"x", "y", "z"};
  for (int i = 0; i < 3; ++i) {
    sensor_msgs::PointField field;
    field.name = names[i];
    field.offset = 4 * i;
    field.datatype = sensor_msgs::PointField::FLOAT32;
    field.count = 1;
    f.cloud.fields.push_back(field);
  }
  f.cloud.point_step = 16;  // x y z + padding, as drivers' XYZRGB
  f.cloud.row_step = f.cloud.point_step * f.cloud.width;
  f.cloud.is_dense = true;
  f.cloud.data.assign(static_cast<size_t>(f.cloud.row_step) * f.cloud.height, 0);
  for (int i = 0; i < static_cast<int>(points.total()); ++i) {
    std::memcpy(&f.cloud.data[i * f.cloud.point_step], &points.at<cv::Vec3f>(i / points.cols, i % points.cols), 12);
  }
  return f;
}

// Publishes the frame at 30 Hz on a thread of its own, each with a fresh stamp; remembers when each
// stamp went out.
class Camera {
 public:
  Camera(ros::NodeHandle& nh, const Frame& frame)
      : frame_(frame),
        image_(nh.advertise<sensor_msgs::Image>(std::string(kNamespace) + "/image", 5)),
        info_(nh.advertise<sensor_msgs::CameraInfo>(std::string(kNamespace) + "/camera_info", 5)),
        cloud_(nh.advertise<sensor_msgs::PointCloud2>(std::string(kNamespace) + "/points", 5)) {}
  ~Camera() { Stop(); }

  void Start() {
    running_ = true;
    thread_ = std::thread([this] { Run(); });
  }
  void Stop() {
    running_ = false;
    if (thread_.joinable()) thread_.join();
  }
  bool Connected() const {
    return image_.getNumSubscribers() > 0 && info_.getNumSubscribers() > 0 && cloud_.getNumSubscribers() > 0;
  }
  std::map<ros::Time, Clock::time_point> Sent() {
    std::lock_guard<std::mutex> lock(mutex_);
    return sent_;
  }
  void Clear() {
    std::lock_guard<std::mutex> lock(mutex_);
    sent_.clear();
  }

 private:
  void Run() {
    const auto period = std::chrono::duration_cast<Clock::duration>(std::chrono::duration<double>(1.0 / kFrameRate));
    Clock::time_point next = Clock::now();
    while (running_ && ros::ok()) {
      std::this_thread::sleep_until(next);
      next += period;
      // A starved camera skips frames, as a driver does; catching up in a burst would flood the queues.
      if (next <= Clock::now()) next = Clock::now() + period;
      const ros::Time stamp = ros::Time::now();
      auto image = boost::make_shared<sensor_msgs::Image>(frame_.image);
      auto info = boost::make_shared<sensor_msgs::CameraInfo>(frame_.info);
      auto cloud = boost::make_shared<sensor_msgs::PointCloud2>(frame_.cloud);
      image->header.stamp = info->header.stamp = cloud->header.stamp = stamp;
      info_.publish(info);
      cloud_.publish(cloud);
      {
        std::lock_guard<std::mutex> lock(mutex_);
        sent_[stamp] = Clock::now();
      }
      image_.publish(image);
    }
  }

  const Frame& frame_;
  ros::Publisher image_, info_, cloud_;
  std::atomic<bool> running_{false};
  std::thread thread_;
  std::mutex mutex_;
  std::map<ros::Time, Clock::time_point> sent_;
};

// Tags by stamp with their arrival time, and the detector's latest diagnostics.
class Listener {
 public:
  explicit Listener(ros::NodeHandle& nh)
      : tags_(nh.subscribe<ArucoTagArray>(std::string(kNamespace) + "/tags", 100,
                                          [this](const ArucoTagArrayConstPtr& msg) {
                                            std::lock_guard<std::mutex> lock(mutex_);
                                            arrived_[msg->header.stamp] = {Clock::now(), msg->tags.size()};
                                          })),
        diagnostics_(nh.subscribe<diagnostic_msgs::DiagnosticArray>(
            "/diagnostics", 10, [this](const diagnostic_msgs::DiagnosticArrayConstPtr& msg) {
              for (const auto& status : msg->status) {
                if (status.name.find("soak/detector") == std::string::npos) continue;
                std::lock_guard<std::mutex> lock(mutex_);
                for (const auto& kv : status.values) values_[kv.key] = kv.value;
              }
            })) {}
  std::map<ros::Time, std::pair<Clock::time_point, size_t>> Arrived() {
    std::lock_guard<std::mutex> lock(mutex_);
    return arrived_;
  }
  // The nodelet subscribes to its inputs before anyone listens (publish_tf), so frames can be
  // answered before this end's tags connection is up: wait for it, not only for the inputs.
  bool Connected() const { return tags_.getNumPublishers() > 0; }
  size_t Count() {
    std::lock_guard<std::mutex> lock(mutex_);
    return arrived_.size();
  }
  void Clear() {
    std::lock_guard<std::mutex> lock(mutex_);
    arrived_.clear();
  }
  std::string Value(const std::string& key) {
    std::lock_guard<std::mutex> lock(mutex_);
    return values_.count(key) ? values_[key] : "";
  }

 private:
  std::mutex mutex_;
  std::map<ros::Time, std::pair<Clock::time_point, size_t>> arrived_;
  std::map<std::string, std::string> values_;
  ros::Subscriber tags_, diagnostics_;
};

bool Load(const Options& o) {
  nodelet::NodeletLoad load;
  load.request.name = std::string(kNamespace) + "/detector";
  load.request.type = "arucotag/DetectorNodelet";
  return ros::service::call(o.manager + "/load_nodelet", load) && load.response.success;
}

bool Unload(const Options& o) {
  nodelet::NodeletUnload unload;
  unload.request.name = std::string(kNamespace) + "/detector";
  return ros::service::call(o.manager + "/unload_nodelet", unload) && unload.response.success;
}

bool WaitFor(const std::function<bool()>& done, double seconds) {
  const auto end = Clock::now() + std::chrono::duration<double>(seconds);
  while (!done()) {
    if (Clock::now() > end || !ros::ok()) return false;
    std::this_thread::sleep_for(std::chrono::milliseconds(20));
  }
  return true;
}

int Main(int argc, char** argv) {
  const Options o = Parse(argc, argv);
  ros::NodeHandle nh;
  ros::AsyncSpinner spinner(2);
  spinner.start();
  for (const char* key : {"dictionary", "tag_size", "use_point_cloud"}) ros::param::del(std::string(kNamespace) + "/detector/" + key);
  ros::param::set(std::string(kNamespace) + "/detector/dictionary", std::string("DICT_5X5_1000"));
  ros::param::set(std::string(kNamespace) + "/detector/tag_size", 0.145);
  ros::param::set(std::string(kNamespace) + "/detector/use_point_cloud", true);

  const Frame frame = MakeFrame(o.photo);
  Camera camera(nh, frame);
  Listener listener(nh);
  std::vector<std::string> failures;

  // ---- Phase 1: the long run ----
  if (!Load(o)) throw Error("cannot load arucotag/DetectorNodelet into " + o.manager);
  if (!WaitFor([&] { return camera.Connected() && listener.Connected(); }, 30.0)) {
    throw Error("the nodelet and the soak never connected");
  }
  std::printf("soak: %.0f s at %.0f Hz: 1280x720 bgr8 photo (2 markers), camera_info, 1280x720 cloud (14.7 MB)\n",
              o.seconds, kFrameRate);
  std::fflush(stdout);
  camera.Start();
  const auto start = Clock::now();
  double cpu_minute = 0.0;
  size_t sent_minute = 0;
  // RSS growth after the first minute: RSS at rest (RestRssMb) with the camera paused for a few
  // seconds once the minute is over, against RSS at rest at the end. The lowest of 1 s samples over
  // 30 s windows while frames flow is printed too, but only as what it is (see RestRssMb).
  std::vector<double> rss_after_settle, rss_last;
  RestRss rest_minute;
  double paused = 0.0;  // s the camera was paused for the first measure
  const double settle = std::min(60.0, o.seconds / 4.0);  // "after the first minute" (shorter runs: a quarter)
  // The nodelet's processing mean over its last 100 frames, once a second: whether it kept up when
  // a frame went unanswered.
  std::vector<std::pair<double, double>> processing;  // (s since start, ms)
  while (Clock::now() - start < std::chrono::duration<double>(o.seconds)) {
    std::this_thread::sleep_for(std::chrono::seconds(1));
    const double t = std::chrono::duration<double>(Clock::now() - start).count();
    const std::string mean = listener.Value(kProcessingMean);
    if (!mean.empty()) processing.emplace_back(t, std::stod(mean));
    if (t >= settle) {
      if (rss_after_settle.empty() && paused == 0.0) {
        const auto pause = Clock::now();
        camera.Stop();
        rest_minute = RestRssMb(o.manager_pid, [&] { return listener.Count(); }, camera.Sent().size());
        camera.Start();
        paused = std::chrono::duration<double>(Clock::now() - pause).count();
        cpu_minute = CpuSeconds(o.manager_pid);
        sent_minute = camera.Sent().size();
        continue;
      }
      const double rss = RssMb(o.manager_pid);
      if (rss_after_settle.size() < 30) rss_after_settle.push_back(rss);
      rss_last.push_back(rss);
      if (rss_last.size() > 30) rss_last.erase(rss_last.begin());
    }
    if (static_cast<int>(t) % 60 == 0) {
      std::printf("  t=%4.0f s  manager RSS %.1f MB  frames sent %zu answered %zu\n", t, RssMb(o.manager_pid),
                  camera.Sent().size(), listener.Count());
      std::fflush(stdout);
    }
  }
  camera.Stop();
  std::this_thread::sleep_for(std::chrono::seconds(2));  // the last frames' answers
  const double cpu_end = CpuSeconds(o.manager_pid);
  const RestRss rest_end = RestRssMb(o.manager_pid, [&] { return listener.Count(); }, camera.Sent().size());
  const double rss_minute = Percentile(rss_after_settle, 0.0), rss_end = Percentile(rss_last, 0.0);
  const auto sent = camera.Sent();
  const auto arrived = listener.Arrived();
  std::vector<double> latency;
  // A frame unanswered while the processing mean of the 100 frames around it (reported in the
  // seconds after it) was above the frame period was lost to overload, which the budget allows.
  const auto overloaded = [&](double sent_at) {
    return std::any_of(processing.begin(), processing.end(), [&](const auto& p) {
      return p.first >= sent_at && p.first <= sent_at + kStatsWindow / kFrameRate + 1.5 && p.second >= 1e3 / kFrameRate;
    });
  };
  size_t answered = 0, with_tags = 0, index = 0, lost_keeping_up = 0;
  std::vector<std::string> unanswered;  // "frame N at T s": where in the run, to tell startup from load
  for (const auto& [stamp, at] : sent) {
    ++index;
    const auto it = arrived.find(stamp);
    if (it == arrived.end()) {
      const double sent_at = std::chrono::duration<double>(at - start).count();
      const bool excused = overloaded(sent_at);
      lost_keeping_up += !excused;
      if (unanswered.size() < 10) {
        char text[80];
        std::snprintf(text, sizeof text, "frame %zu at %.2f s%s", index, sent_at, excused ? " (overloaded)" : "");
        unanswered.push_back(text);
      }
      continue;
    }
    ++answered;
    with_tags += it->second.second == 2;
    latency.push_back(std::chrono::duration<double, std::milli>(it->second.first - at).count());
  }
  double mean_ms = 0.0;
  for (const auto& p : processing) mean_ms += p.second / processing.size();
  const auto overloaded_seconds = std::count_if(processing.begin(), processing.end(), [](const auto& p) {
    return p.second >= 1e3 / kFrameRate;
  });
  const double cpu_per_frame = (cpu_end - cpu_minute) * 1e3 / std::max<size_t>(1, sent.size() - sent_minute);
  const double growth = rest_end.mb - rest_minute.mb;
  std::printf("soak: frames sent %zu (%.1f Hz), answered %zu (%.2f %%), both markers in %zu; latency publish -> tags "
              "median %.2f ms, p99 %.2f ms; processing mean %.2f ms (frame period %.1f ms); manager CPU %.2f ms per "
              "frame; RSS at rest %.2f MB after %.0f s (samples within %.2f MB; camera paused %.1f s), %.2f MB at the "
              "end (within %.2f MB): growth %+.2f MB; while running, lowest 1 s sample %.1f MB over the 30 s after "
              "%.0f s, %.1f MB over the last 30 s (%+.1f MB, not a growth figure)\n",
              sent.size(), sent.size() / (o.seconds - paused), answered,
              100.0 * answered / std::max<size_t>(1, sent.size()), with_tags, Percentile(latency, 0.5),
              Percentile(latency, 0.99), mean_ms, 1e3 / kFrameRate, cpu_per_frame, rest_minute.mb, settle,
              rest_minute.spread, paused, rest_end.mb, rest_end.spread, growth, rss_minute, settle, rss_end,
              rss_end - rss_minute);
  if (answered != sent.size()) {
    std::string which;
    for (const auto& u : unanswered) which += (which.empty() ? "" : ", ") + u;
    // The nodelet's own counts tell a frame lost on the way in from one it dropped or failed on.
    std::printf("soak: unanswered: %s; %zu while the nodelet kept up; its processing mean was above the frame "
                "period in %ld of %zu seconds; the nodelet received %s frames and processed %s\n",
                which.c_str(), lost_keeping_up, static_cast<long>(overloaded_seconds), processing.size(),
                listener.Value("frames received").c_str(), listener.Value("frames processed").c_str());
  }
  if (growth >= 1.0) failures.push_back("RSS grew " + std::to_string(growth) + " MB after the first minute (budget 1)");
  if (lost_keeping_up > 0) {
    failures.push_back(std::to_string(lost_keeping_up) + " frames unanswered while processing kept up");
  }
  if (with_tags != answered) failures.push_back(std::to_string(answered - with_tags) + " answers without both markers");

  // ---- Phase 2: load/unload with subscribers attached and frames flowing ----
  // Answers per cycle are not counted against sends here: at rest once none came for 1 s.
  const auto rest_mb = [&] {
    return RestRssMb(o.manager_pid, [&] { return listener.Count(); }, std::numeric_limits<size_t>::max()).mb;
  };
  camera.Start();
  double rss_warm = 0.0;
  int published_again = 0;
  for (int cycle = 0; cycle < o.cycles; ++cycle) {
    if (!Unload(o)) {
      failures.push_back("unload failed in cycle " + std::to_string(cycle));
      break;
    }
    listener.Clear();
    if (!Load(o)) {
      failures.push_back("load failed in cycle " + std::to_string(cycle));
      break;
    }
    published_again += WaitFor([&] { return listener.Count() > 0; }, 10.0);
    if (cycle == std::min(9, o.cycles - 1)) {  // after warm-up: RSS at rest, as in phase 1
      camera.Stop();
      rss_warm = rest_mb();
      camera.Start();
    }
  }
  camera.Stop();
  const double rss_cycles = rest_mb();
  nodelet::NodeletList list;
  const bool alive = ros::service::call(o.manager + "/list", list);
  std::printf("soak: %d load/unload cycles with frames flowing: %d published again; manager %s; RSS at rest %.1f MB "
              "after 10 cycles, %.1f MB after %d (growth %+.2f MB)\n",
              o.cycles, published_again, alive ? "alive" : "DEAD", rss_warm, rss_cycles, o.cycles,
              rss_cycles - rss_warm);
  if (published_again != o.cycles) failures.push_back("only " + std::to_string(published_again) + " cycles published");
  if (!alive) failures.push_back("the manager stopped answering");
  if (rss_cycles - rss_warm >= 2.0) {
    failures.push_back("RSS grew " + std::to_string(rss_cycles - rss_warm) + " MB over the cycles (budget 2)");
  }
  Unload(o);
  spinner.stop();
  for (const auto& f : failures) std::printf("soak: FAIL: %s\n", f.c_str());
  std::printf("soak: %s\n", failures.empty() ? "PASS" : "FAIL");
  return failures.empty() ? 0 : 1;
}

}  // namespace
}  // namespace arucotag::soak

int main(int argc, char** argv) {
  ros::init(argc, argv, "arucotag_soak", ros::init_options::NoSigintHandler);
  try {
    return arucotag::soak::Main(argc, argv);
  } catch (const std::exception& e) {
    std::fprintf(stderr, "soak: %s\n", e.what());
    return 2;
  }
}

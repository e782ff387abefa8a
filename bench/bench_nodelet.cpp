// bench_nodelet: the nodelet row of the benchmark, the detector nodelet end to end inside a nodelet manager.
// Loads arucotag/DetectorNodelet in this process with nodelet::Loader, publishes the benchmark's
// frames (bgr8 sensor_msgs/Image + camera_info with the same stamp) by shared pointer, so roscpp
// hands them over without serialising, and times from publish() to the arrival of the tags with
// that stamp. The same frames also go through the pipeline row, the core pipeline the nodelet runs
// (PreprocessFrame + Detect + EstimatePoseFromPNP), alternating with the nodelet frame by frame in this
// process, so the nodelet's overhead is measured under the same load. Writes JSON rows for
// bench/report.py. Needs a ROS master (bench/run.sh starts one).
//
//   bench_nodelet --data test/data --cache DIR --json FILE [--frames 6] [--sequence-frames 100] [--reps 5]
//                 [--sets 'name substring|...']
#include <arucotag/ros/messages.hpp>  // first: renames the generated ArucoTag message
#include <arucotag/TagTracks.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <condition_variable>
#include <cstdio>
#include <fstream>
#include <map>
#include <mutex>
#include <string>
#include <thread>
#include <vector>

#include <cv_bridge/cv_bridge.h>
#include <nodelet/loader.h>
#include <ros/ros.h>
#include <sensor_msgs/CameraInfo.h>
#include <sensor_msgs/Image.h>

#include <arucotag/arucotag.hpp>

#include "frames.hpp"
#include "stats.hpp"
#include "tool_main.hpp"

namespace arucotag::bench {
namespace {

using Clock = std::chrono::steady_clock;

constexpr const char* kNamespace = "/arucotag_bench";

// Messages (the tags, the tracks) as they arrive, by stamp, with their arrival time.
template <class Msg>
class Waiter {
 public:
  using ConstPtr = boost::shared_ptr<const Msg>;
  void Add(const ConstPtr& msg) {
    {
      std::lock_guard<std::mutex> lock(mutex_);
      arrived_[msg->header.stamp] = {Clock::now(), msg};
    }
    cv_.notify_all();
  }
  bool Wait(const ros::Time& stamp, double timeout_s, Clock::time_point& at, ConstPtr& msg) {
    std::unique_lock<std::mutex> lock(mutex_);
    const bool ok = cv_.wait_for(lock, std::chrono::duration<double>(timeout_s), [&] { return arrived_.count(stamp) > 0; });
    if (!ok) return false;
    at = arrived_[stamp].first;
    msg = arrived_[stamp].second;
    arrived_.erase(stamp);
    return true;
  }

 private:
  std::mutex mutex_;
  std::condition_variable cv_;
  std::map<ros::Time, std::pair<Clock::time_point, ConstPtr>> arrived_;
};
using TagsWaiter = Waiter<ArucoTagArray>;

sensor_msgs::CameraInfoPtr Info(const CameraModel& camera, const cv::Size& size) {
  auto info = boost::make_shared<sensor_msgs::CameraInfo>();
  info->header.frame_id = "bench_optical";
  info->width = size.width;
  info->height = size.height;
  info->distortion_model = "plumb_bob";
  info->D = camera.distortion.empty() ? std::vector<double>(5, 0.0) : camera.distortion;
  for (int i = 0; i < 9; ++i) info->K[i] = camera.K.val[i];
  info->R = {1, 0, 0, 0, 1, 0, 0, 0, 1};
  for (int r = 0; r < 3; ++r) {
    for (int c = 0; c < 3; ++c) info->P[r * 4 + c] = camera.K(r, c);
  }
  return info;
}

struct Row {
  std::string name;
  std::vector<double> wall, cpu, core_wall;  // the nodelet, and the pipeline side by side, frame by frame
  int found = 0, expected = 0, false_positives = 0, lost = 0;
};

// The median over a row's frames of the nodelet's time over the pipeline's on the same frame, timed
// one after the other: what the machine's drift between the two moves least.
double PairedRatioMedian(const Row& row) {
  std::vector<double> ratios(row.wall.size());
  for (size_t i = 0; i < ratios.size(); ++i) ratios[i] = row.wall[i] / std::max(1e-9, row.core_wall[i]);
  return Percentile(ratios, 0.5);
}

struct Stream {
  int sent = 0, answered = 0;
  std::vector<double> latency, core;  // ms
};

Stream StreamAt30Hz(const FrameSet& set, ros::Publisher& image_pub, ros::Publisher& info_pub, TagsWaiter& waiter,
                    double& stamp_s) {
  constexpr int kFrames = 300;  // 10 s
  constexpr auto kPeriod = std::chrono::microseconds(33333);
  std::vector<sensor_msgs::ImagePtr> images;
  for (const Frame& f : set.frames) {
    std_msgs::Header header;
    header.frame_id = "bench_optical";
    images.push_back(cv_bridge::CvImage(header, "bgr8", f.bgr).toImageMsg());
  }
  auto info = Info(set.camera, set.frames.front().bgr.size());
  info->header.stamp = ros::Time(stamp_s);
  info_pub.publish(info);  // once: the nodelet keeps the latest
  std::this_thread::sleep_for(std::chrono::milliseconds(200));

  Stream stream;
  std::vector<std::pair<ros::Time, Clock::time_point>> sent;
  Clock::time_point next = Clock::now();
  for (int i = 0; i < kFrames; ++i) {
    std::this_thread::sleep_until(next);
    next += kPeriod;
    stamp_s += 1.0 / 30.0;
    auto image = boost::make_shared<sensor_msgs::Image>(*images[i % images.size()]);
    image->header.stamp = ros::Time(stamp_s);
    sent.emplace_back(image->header.stamp, Clock::now());
    image_pub.publish(image);
    ++stream.sent;
  }
  for (const auto& [stamp, t0] : sent) {
    Clock::time_point at;
    ArucoTagArrayConstPtr msg;
    if (!waiter.Wait(stamp, 2.0, at, msg)) continue;
    ++stream.answered;
    stream.latency.push_back(std::chrono::duration<double, std::milli>(at - t0).count());
  }
  // The core alone on the same frames, in the same order (tracking state carried as in the stream)
  // and at the same 30 Hz cadence: back to back it would run with hot caches and an awake CPU, which
  // a camera's frames never see (measured: 1.7x apart for that reason alone).
  DetectorConfig config;
  config.dictionary = set.dictionary;
  config.default_side_length = set.side_length;
  const Detector core(config);
  next = Clock::now();
  for (int i = 0; i < kFrames; ++i) {
    std::this_thread::sleep_until(next);
    next += kPeriod;
    const Frame& f = set.frames[i % set.frames.size()];
    const Clock::time_point c0 = Clock::now();
    cv::Mat grey;
    PreprocessFrame(f.bgr, grey);
    std::vector<ArucoTag> tags = Detect(grey, core, set.camera);
    for (auto& tag : tags) EstimatePoseFromPNP(set.camera, tag);
    stream.core.push_back(std::chrono::duration<double, std::milli>(Clock::now() - c0).count());
  }
  return stream;
}

int Main(int argc, char** argv) {
  const Options options = ParseOptions(argc, argv, "nodelet.json");
  const std::string& json = options.json;
  const int reps = options.reps;
  if (!ros::master::check()) throw Error("no ROS master at " + ros::master::getURI() + " (bench/run.sh starts one)");

  std::vector<FrameSet> sets = AllSets(options);
  sets.erase(std::remove_if(sets.begin(), sets.end(), [&](const FrameSet& s) { return !Selected(options.sets, s.name); }),
             sets.end());

  ros::NodeHandle nh;
  const std::string detector = std::string(kNamespace) + "/detector";
  // Raw only: the bench times the raw path (auto would also subscribe <image>/compressed).
  ros::param::set(detector + "/image_transport", std::string("raw"));
  ros::param::set(detector + "/queue_size", 5);
  // The core's default refinement, whatever the nodelet would pick without a yaml: pipeline and nodelet must
  // run the same pipeline.
  const char* refinement[] = {"none", "subpix", "contour", "apriltag", "edge"};
  ros::param::set(detector + "/corner_refinement",
                  std::string(refinement[static_cast<int>(DetectorConfig().corner_refinement)]));

  TagsWaiter waiter;
  ros::Subscriber tags_sub = nh.subscribe<ArucoTagArray>(std::string(kNamespace) + "/tags", 20,
                                                         [&](const ArucoTagArrayConstPtr& msg) { waiter.Add(msg); });
  // The nodelet publishes the tags first and its tracks after its tracker's update: the pipeline
  // alongside is timed once the tracks are out too, so the nodelet's work on the frame does not
  // share the cores with it.
  Waiter<TagTracks> tracks_waiter;
  ros::Subscriber tracks_sub = nh.subscribe<TagTracks>(
      std::string(kNamespace) + "/tracks", 20, [&](const TagTracksConstPtr& msg) { tracks_waiter.Add(msg); });
  ros::Publisher image_pub = nh.advertise<sensor_msgs::Image>(std::string(kNamespace) + "/image", 5);
  ros::Publisher info_pub = nh.advertise<sensor_msgs::CameraInfo>(std::string(kNamespace) + "/camera_info", 5);
  ros::AsyncSpinner spinner(1);
  spinner.start();

  nodelet::Loader loader(false);  // in this process, no load/unload services
  if (!loader.load(detector, "arucotag/DetectorNodelet", {}, {})) throw Error("cannot load arucotag/DetectorNodelet");
  for (int i = 0; i < 200 && (image_pub.getNumSubscribers() == 0 || info_pub.getNumSubscribers() == 0 ||
                              tags_sub.getNumPublishers() == 0 || tracks_sub.getNumPublishers() == 0);
       ++i) {
    std::this_thread::sleep_for(std::chrono::milliseconds(50));
  }
  if (image_pub.getNumSubscribers() == 0) throw Error("the nodelet did not subscribe to " + image_pub.getTopic());

  std::vector<Row> rows;
  double stamp_s = 1000.0;
  std::string loaded = "DICT_4X4_50 0.150000";  // what the first load read (defaults)
  // Dictionary and size are read when the nodelet loads: reload it when a set needs others.
  const auto load_for = [&](const FrameSet& set) {
    const std::string wanted = set.dictionary + " " + std::to_string(set.side_length);
    if (wanted == loaded) return;
    ros::param::set(detector + "/dictionary", set.dictionary);
    ros::param::set(detector + "/tag_size", set.side_length);
    loader.unload(detector);
    if (!loader.load(detector, "arucotag/DetectorNodelet", {}, {})) throw Error("cannot reload the nodelet");
    loaded = wanted;
    for (int i = 0; i < 200 && image_pub.getNumSubscribers() == 0; ++i) {
      std::this_thread::sleep_for(std::chrono::milliseconds(50));
    }
  };
  for (const FrameSet& set : sets) {
    load_for(set);
    Row row;
    row.name = set.name;
    // Messages are made before timing: a camera driver hands over a filled message.
    std::vector<sensor_msgs::ImagePtr> images;
    std::vector<sensor_msgs::CameraInfoPtr> infos;
    for (const Frame& f : set.frames) {
      std_msgs::Header header;
      header.frame_id = "bench_optical";
      images.push_back(cv_bridge::CvImage(header, "bgr8", f.bgr).toImageMsg());
      infos.push_back(Info(set.camera, f.bgr.size()));
    }
    // The pipeline as the nodelet runs it: one Detector for the whole stream, as configured there.
    DetectorConfig config;
    config.dictionary = set.dictionary;
    config.default_side_length = set.side_length;
    const Detector core(config);
    const auto run_core = [&](const Frame& f) {
      const Clock::time_point c0 = Clock::now();
      cv::Mat grey;
      PreprocessFrame(f.bgr, grey);
      std::vector<ArucoTag> tags = Detect(grey, core, set.camera);
      for (auto& tag : tags) EstimatePoseFromPNP(set.camera, tag);
      return std::chrono::duration<double, std::milli>(Clock::now() - c0).count();
    };
    // At least kMinTimedFrames frames timed: a set of two or three photos at make bench's 8 passes
    // gave 16-24 timings, whose nodelet-over-pipeline ratio moved by up to 0.3 from run to run.
    constexpr int kMinTimedFrames = 48;
    const int frames = static_cast<int>(set.frames.size());
    const int passes = set.sequence ? std::max(1, reps / 2)
                                    : std::max(reps, (kMinTimedFrames + frames - 1) / std::max(1, frames));
    for (int rep = -1; rep < passes; ++rep) {  // rep -1 warms up (first frame only)
      for (size_t k = 0; k < set.frames.size(); ++k) {
        stamp_s += 0.1;
        const ros::Time stamp(stamp_s);
        // A fresh message per publish: subscribers get const pointers and may keep them.
        auto image = boost::make_shared<sensor_msgs::Image>(*images[k]);
        auto info = boost::make_shared<sensor_msgs::CameraInfo>(*infos[k]);
        image->header.stamp = info->header.stamp = stamp;
        const double c0 = CpuMs();
        const Clock::time_point t0 = Clock::now();
        info_pub.publish(info);
        image_pub.publish(image);
        Clock::time_point at;
        ArucoTagArrayConstPtr msg;
        if (!waiter.Wait(stamp, 5.0, at, msg)) {
          ++row.lost;
          continue;
        }
        const double cpu = CpuMs() - c0;
        Clock::time_point tracks_at;
        TagTracksConstPtr tracks;
        tracks_waiter.Wait(stamp, 5.0, tracks_at, tracks);
        if (rep < 0) break;
        row.wall.push_back(std::chrono::duration<double, std::milli>(at - t0).count());
        row.cpu.push_back(cpu);
        row.core_wall.push_back(run_core(set.frames[k]));
        if (rep == 0) {
          std::vector<int> ids;
          std::vector<std::array<cv::Point2f, 4>> corners;
          for (const auto& t : msg->tags) {
            ids.push_back(t.id);
            std::array<cv::Point2f, 4> q;
            for (int c = 0; c < 4; ++c) q[c] = cv::Point2f(t.corners[c].x, t.corners[c].y);
            corners.push_back(q);
          }
          const Score s = ScoreFrame(set.frames[k], ids, corners);
          row.found += s.found;
          row.expected += s.expected;
          row.false_positives += s.false_positives;
        }
      }
    }
    std::fprintf(stderr,
                 "  %-28s nodelet %7.2f ms median, pipeline alongside %7.2f ms, paired ratio median %.2f (%zu frames "
                 "timed, %d lost)\n",
                 set.name.c_str(), Percentile(row.wall, 0.5), Percentile(row.core_wall, 0.5),
                 PairedRatioMedian(row), row.wall.size(), row.lost);
    rows.push_back(row);
  }
  // A camera at 30 Hz: frames go out on the clock, whether or not the last one was answered, and
  // each is timed from publish() to its tags. The core's own time on the same frames, measured
  // after the stream, is the yardstick: latency should be the processing time, never a frame more.
  Stream stream;
  const auto sequence = std::find_if(sets.begin(), sets.end(), [](const FrameSet& s) { return s.sequence; });
  if (sequence != sets.end()) {
    load_for(*sequence);
    stream = StreamAt30Hz(*sequence, image_pub, info_pub, waiter, stamp_s);
    std::fprintf(stderr,
                 "  30 Hz stream (%s): %d of %d frames answered; latency median %.2f ms, p99 %.2f ms; core alone "
                 "median %.2f ms, p99 %.2f ms; latency / core %.2f (median), %.2f (p99)\n",
                 sequence->name.c_str(), stream.answered, stream.sent, Percentile(stream.latency, 0.5),
                 Percentile(stream.latency, 0.99), Percentile(stream.core, 0.5), Percentile(stream.core, 0.99),
                 Percentile(stream.latency, 0.5) / std::max(1e-9, Percentile(stream.core, 0.5)),
                 Percentile(stream.latency, 0.99) / std::max(1e-9, Percentile(stream.core, 0.99)));
  }
  loader.unload(detector);
  spinner.stop();

  std::ofstream out(json);
  out.precision(6);
  out << "{\n  \"tool\": \"bench_nodelet\",\n  \"note\": \"arucotag/DetectorNodelet loaded with nodelet::Loader in the benchmark "
         "process; bgr8 image + camera_info published by shared pointer (no serialisation), raw transport; time from "
         "publish() to the tags message arriving at a subscriber in the same process\",\n  \"sets\": [\n";
  for (size_t i = 0; i < rows.size(); ++i) {
    const Row& r = rows[i];
    // A set whose frames were all lost has no times: null, not 0 ms.
    double mean = r.wall.empty() ? NAN : 0.0;
    for (double w : r.wall) mean += w / r.wall.size();
    out << "    {\"name\": \"" << r.name << "\", \"method\": {\"label\": \"nodelet in a manager, publish to tags (own run)\", "
        << "\"median_ms\": " << JsonNumber(Percentile(r.wall, 0.5)) << ", \"p90_ms\": " << JsonNumber(Percentile(r.wall, 0.9))
        << ", \"mean_ms\": " << JsonNumber(mean) << ", \"cpu_median_ms\": " << JsonNumber(Percentile(r.cpu, 0.5))
        << ", \"calls\": " << r.wall.size() << ", \"lost\": " << r.lost << ", \"found\": " << r.found
        << ", \"expected\": " << r.expected << ", \"false_positives\": " << r.false_positives
        << "}, \"core_side_by_side\": {\"median_ms\": " << JsonNumber(Percentile(r.core_wall, 0.5))
        << ", \"p90_ms\": " << JsonNumber(Percentile(r.core_wall, 0.9))
        << ", \"paired_ratio_median\": " << JsonNumber(PairedRatioMedian(r)) << "}}"
        << (i + 1 < rows.size() ? "," : "") << "\n";
  }
  out << "  ],\n  \"stream_30hz\": {\"sent\": " << stream.sent << ", \"answered\": " << stream.answered
      << ", \"latency_median_ms\": " << JsonNumber(Percentile(stream.latency, 0.5))
      << ", \"latency_p99_ms\": " << JsonNumber(Percentile(stream.latency, 0.99))
      << ", \"core_median_ms\": " << JsonNumber(Percentile(stream.core, 0.5))
      << ", \"core_p99_ms\": " << JsonNumber(Percentile(stream.core, 0.99)) << "}\n}\n";
  std::fprintf(stderr, "bench_nodelet: wrote %s\n", json.c_str());
  return 0;
}

}  // namespace
}  // namespace arucotag::bench

int main(int argc, char** argv) {
  ros::init(argc, argv, "arucotag_bench_nodelet", ros::init_options::NoSigintHandler);
  return arucotag::bench::RunTool("bench_nodelet", arucotag::bench::Main, argc, argv);
}

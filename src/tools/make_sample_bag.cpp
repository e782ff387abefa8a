// make_sample_bag: writes the sample recording that `make demo`, the replay tests and the rviz
// screenshot use. A rover's stereo camera approaches and passes a URC post (id 1 on three faces)
// with five more DICT_4X4_50 markers at 2-15 m; light, exposure and motion blur change over time.
//
//   make_sample_bag [--output sample.bag] [--start 0] [--duration 15] [--rate 15] [--threads N]
//                   [--supersample 4] [--compression lz4|bz2|none] [--summary]
//
// Topics (ZED-style, what launch/rover.launch expects):
//   /zed/left/image_rect_color            sensor_msgs/Image bgr8 1280x720, frame zed_left_camera_optical_frame
//   /zed/left/camera_info                 sensor_msgs/CameraInfo (rectified, no distortion)
//   /zed/point_cloud/cloud_registered     sensor_msgs/PointCloud2 organized float32 x y z, frame zed_left_camera_frame
//   /tf                                   odom -> base_link at 3x the frame rate
//   /tf_static (latched)                  base_link -> zed_left_camera_frame -> ..._optical_frame, odom -> truth_<marker>
//   /truth/tags                           arucotag/ArucoTagTruth, one per image, same stamp
// Every frame is a function of its time only: the output is identical byte for byte on every run,
// and a --start/--duration excerpt holds the same frames as the full recording.
#include <arucotag/ros/messages.hpp>  // first: renames the generated ArucoTag message
#include <arucotag/ArucoTagTruth.h>

#include <algorithm>
#include <atomic>
#include <chrono>
#include <condition_variable>
#include <cstdio>
#include <filesystem>
#include <iostream>
#include <map>
#include <mutex>
#include <string>
#include <thread>

#include <geometry_msgs/TransformStamped.h>
#include <opencv2/calib3d.hpp>
#include <opencv2/core/utility.hpp>
#include <opencv2/imgproc.hpp>
#include <rosbag/bag.h>
#include <ros/message_traits.h>
#include <sensor_msgs/CameraInfo.h>
#include <sensor_msgs/Image.h>
#include <sensor_msgs/PointCloud2.h>
#include <tf2/LinearMath/Matrix3x3.h>
#include <tf2/LinearMath/Quaternion.h>
#include <tf2_msgs/TFMessage.h>

#include "../replay/sample_scene.hpp"

namespace {

using arucotag::replay::SampleFrame;
using arucotag::replay::SampleScene;
using arucotag::replay::Transform;

const ros::Time kEpoch(1700000000, 0);  // scene time 0; fixed so every run writes the same stamps
const char* const kOdom = "odom";
const char* const kBase = "base_link";
const char* const kBody = "zed_left_camera_frame";
const char* const kOptical = "zed_left_camera_optical_frame";
const char* const kImageTopic = "/zed/left/image_rect_color";
const char* const kInfoTopic = "/zed/left/camera_info";
const char* const kCloudTopic = "/zed/point_cloud/cloud_registered";
const char* const kTruthTopic = "/truth/tags";

struct Args {
  std::string output = "sample.bag";
  double start = 0.0, duration = 15.0, rate = 15.0;
  int threads = static_cast<int>(std::max(1u, std::thread::hardware_concurrency()));
  int supersample = 4;
  std::string compression = "lz4";
  bool summary = false;
};

void Usage() {
  std::cerr << "usage: make_sample_bag [--output FILE] [--start S] [--duration S] [--rate HZ] [--threads N]\n"
               "                       [--supersample N] [--compression lz4|bz2|none] [--summary]\n"
               "  Writes the sample recording (defaults: sample.bag, 0-15 s at 15 Hz, lz4). --start/--duration/--rate\n"
               "  cut an excerpt with the same frames; --summary prints what each marker shows and writes nothing.\n";
}

Args Parse(int argc, char** argv) {
  Args args;
  for (int i = 1; i < argc; ++i) {
    const std::string arg = argv[i];
    const auto value = [&]() -> std::string {
      if (i + 1 >= argc) throw std::runtime_error("missing value after " + arg);
      return argv[++i];
    };
    if (arg == "--output") args.output = value();
    else if (arg == "--start") args.start = std::stod(value());
    else if (arg == "--duration") args.duration = std::stod(value());
    else if (arg == "--rate") args.rate = std::stod(value());
    else if (arg == "--threads") args.threads = std::stoi(value());
    else if (arg == "--supersample") args.supersample = std::stoi(value());
    else if (arg == "--compression") args.compression = value();
    else if (arg == "--summary") args.summary = true;
    else if (arg == "--help" || arg == "-h") throw std::runtime_error("");
    else throw std::runtime_error("unknown argument " + arg);
  }
  if (!(args.start >= 0) || !(args.duration > 0) || !(args.rate > 0) || args.threads < 1 || args.supersample < 1)
    throw std::runtime_error("need --start >= 0, --duration > 0, --rate > 0, --threads >= 1, --supersample >= 1");
  if (args.compression != "lz4" && args.compression != "bz2" && args.compression != "none")
    throw std::runtime_error("--compression must be lz4, bz2 or none");
  return args;
}

ros::Time Stamp(double t) { return kEpoch + ros::Duration(t); }

geometry_msgs::Quaternion ToQuaternion(const cv::Matx33d& r) {
  tf2::Quaternion q;
  tf2::Matrix3x3(r(0, 0), r(0, 1), r(0, 2), r(1, 0), r(1, 1), r(1, 2), r(2, 0), r(2, 1), r(2, 2)).getRotation(q);
  geometry_msgs::Quaternion out;
  out.x = q.x();
  out.y = q.y();
  out.z = q.z();
  out.w = q.w();
  return out;
}

geometry_msgs::TransformStamped ToTransform(const Transform& t, const std::string& parent, const std::string& child,
                                            const ros::Time& stamp) {
  geometry_msgs::TransformStamped out;
  out.header.stamp = stamp;
  out.header.frame_id = parent;
  out.child_frame_id = child;
  out.transform.translation.x = t.translation()[0];
  out.transform.translation.y = t.translation()[1];
  out.transform.translation.z = t.translation()[2];
  out.transform.rotation = ToQuaternion(t.rotation());
  return out;
}

sensor_msgs::CameraInfo CameraInfoFor(const SampleScene& scene, const std_msgs::Header& header) {
  const auto& camera = scene.Camera();
  sensor_msgs::CameraInfo info;
  info.header = header;
  info.width = camera.size.width;
  info.height = camera.size.height;
  info.distortion_model = "plumb_bob";
  info.D.assign(5, 0.0);  // rectified
  for (int i = 0; i < 9; ++i) info.K[i] = camera.K.val[i];
  info.R = {1, 0, 0, 0, 1, 0, 0, 0, 1};
  for (int r = 0; r < 3; ++r)
    for (int c = 0; c < 3; ++c) info.P[r * 4 + c] = camera.K(r, c);
  return info;
}

// The pixels of `mat`, row after row without padding, as a message's data array.
std::vector<uint8_t> PackedRows(const cv::Mat& mat) {
  const size_t row = mat.cols * mat.elemSize();
  std::vector<uint8_t> data(row * mat.rows);
  for (int v = 0; v < mat.rows; ++v) std::copy_n(mat.ptr<uint8_t>(v), row, &data[v * row]);
  return data;
}

sensor_msgs::Image ImageFor(const cv::Mat& bgr, const std_msgs::Header& header) {
  sensor_msgs::Image image;
  image.header = header;
  image.height = bgr.rows;
  image.width = bgr.cols;
  image.encoding = "bgr8";
  image.step = static_cast<uint32_t>(bgr.cols * bgr.elemSize());
  image.data = PackedRows(bgr);
  return image;
}

sensor_msgs::PointCloud2 CloudFor(const cv::Mat& xyz, const std_msgs::Header& header) {
  sensor_msgs::PointCloud2 cloud;
  cloud.header = header;
  cloud.height = xyz.rows;
  cloud.width = xyz.cols;
  for (const char* name : {"x", "y", "z"}) {
    sensor_msgs::PointField field;
    field.name = name;
    field.offset = static_cast<uint32_t>(4 * cloud.fields.size());
    field.datatype = sensor_msgs::PointField::FLOAT32;
    field.count = 1;
    cloud.fields.push_back(field);
  }
  cloud.is_bigendian = false;
  cloud.point_step = 12;
  cloud.row_step = cloud.point_step * cloud.width;
  cloud.is_dense = false;  // NaN holes
  cloud.data = PackedRows(xyz);
  return cloud;
}

arucotag::ArucoTagTruth TruthFor(const SampleFrame& frame, const std_msgs::Header& header) {
  arucotag::ArucoTagTruth truth;
  truth.header = header;
  for (const auto& tag : frame.truth) {
    arucotag::ArucoTagMsg msg;
    msg.id = tag.id;
    for (int i = 0; i < 4; ++i) {
      msg.corners[i].x = tag.corners[i].x;
      msg.corners[i].y = tag.corners[i].y;
    }
    msg.center.x = tag.centre.x;
    msg.center.y = tag.centre.y;
    msg.side_length = tag.side;
    msg.pose_source = arucotag::ArucoTagMsg::NONE;
    msg.pose.position.x = tag.tvec[0];
    msg.pose.position.y = tag.tvec[1];
    msg.pose.position.z = tag.tvec[2];
    cv::Matx33d r;
    cv::Rodrigues(tag.rvec, r);
    msg.pose.orientation = ToQuaternion(r);
    msg.distance = tag.distance;
    msg.yaw = tag.yaw;
    msg.reprojection_error = msg.ambiguity = msg.depth_disagreement = std::numeric_limits<double>::quiet_NaN();
    truth.tags.push_back(msg);
    truth.names.push_back(tag.name);
    truth.complete.push_back(tag.complete);
    truth.obliquity.push_back(tag.obliquity);
  }
  return truth;
}

// A latched connection, so `rosbag play` republishes /tf_static to late subscribers.
template <class Message>
boost::shared_ptr<ros::M_string> LatchedHeader() {
  auto header = boost::make_shared<ros::M_string>();
  (*header)["type"] = ros::message_traits::datatype<Message>();
  (*header)["md5sum"] = ros::message_traits::md5sum<Message>();
  (*header)["message_definition"] = ros::message_traits::definition<Message>();
  (*header)["callerid"] = "/make_sample_bag";
  (*header)["latching"] = "1";
  return header;
}

// Markers each truth frame saw: how often, how often whole and >= 20 px, at what range.
void PrintSummary(const SampleScene& scene, const std::vector<double>& times) {
  struct Stats {
    int facing = 0, complete = 0, big = 0;
    double near = 1e9, far = 0, max_px = 0;
  };
  std::map<std::string, Stats> stats;
  int two_faces = 0;
  for (double t : times) {
    int post_faces = 0;
    for (const auto& tag : scene.Truth(t)) {
      Stats& s = stats[tag.name];
      const double px = std::sqrt(std::abs(cv::contourArea(std::vector<cv::Point2f>(tag.corners.begin(), tag.corners.end()))));
      ++s.facing;
      s.complete += tag.complete;
      const bool big = tag.complete && px >= 20.0;
      s.big += big;
      post_faces += big && tag.name.rfind("post_", 0) == 0;
      if (tag.complete) {
        s.near = std::min(s.near, tag.distance);
        s.far = std::max(s.far, tag.distance);
        s.max_px = std::max(s.max_px, px);
      }
    }
    two_faces += post_faces >= 2;
  }
  std::printf("%-10s %7s %9s %9s %14s %7s\n", "marker", "facing", "complete", ">=20px", "range (m)", "max px");
  for (const auto& [name, s] : stats) {
    std::printf("%-10s %7d %9d %9d %6.1f - %5.1f %7.0f\n", name.c_str(), s.facing, s.complete, s.big,
                s.complete ? s.near : 0.0, s.far, s.max_px);
  }
  std::printf("frames with two post faces >= 20 px: %d of %zu\n", two_faces, times.size());
}

}  // namespace

int main(int argc, char** argv) {
  Args args;
  try {
    args = Parse(argc, argv);
  } catch (const std::exception& e) {
    if (*e.what()) std::cerr << "make_sample_bag: " << e.what() << "\n";
    Usage();
    return *e.what() ? 2 : 0;
  }
  const auto started = std::chrono::steady_clock::now();
  const int frames = std::max(1, static_cast<int>(std::lround(args.duration * args.rate)));
  std::vector<double> times(frames);
  for (int k = 0; k < frames; ++k) times[k] = args.start + k / args.rate;

  arucotag::replay::SampleOptions options;
  options.supersample = args.supersample;
  const SampleScene scene(options);
  if (args.summary) {
    PrintSummary(scene, times);
    return 0;
  }

  rosbag::Bag bag;
  try {
    const auto parent = std::filesystem::path(args.output).parent_path();
    if (!parent.empty()) std::filesystem::create_directories(parent);
    bag.open(args.output + ".active", rosbag::bagmode::Write);
    bag.setCompression(args.compression == "lz4"   ? rosbag::compression::LZ4
                       : args.compression == "bz2" ? rosbag::compression::BZ2
                                                   : rosbag::compression::Uncompressed);
    bag.setChunkThreshold(8 * 1024 * 1024);
  } catch (const std::exception& e) {
    std::cerr << "make_sample_bag: cannot write " << args.output << ": " << e.what() << "\n";
    return 1;
  }

  // Static frames first, stamped at the first image.
  const ros::Time first = Stamp(times.front());
  tf2_msgs::TFMessage statics;
  statics.transforms.push_back(ToTransform(SampleScene::MastMount(), kBase, kBody, first));
  statics.transforms.push_back(ToTransform(SampleScene::OpticalInBody(), kBody, kOptical, first));
  for (const auto& m : scene.Markers()) statics.transforms.push_back(ToTransform(m.pose, kOdom, "truth_" + m.name, first));
  bag.write("/tf_static", first, statics, LatchedHeader<tf2_msgs::TFMessage>());

  // Frames render on worker threads (each frame is independent) and are written in time order,
  // with the odometry TF (3 per frame, one at each image stamp) interleaved.
  cv::setNumThreads(args.threads > 1 ? 1 : -1);  // parallel across frames, not inside one
  std::mutex mutex;
  std::condition_variable ready, room;
  std::map<int, SampleFrame> done;
  std::atomic<int> next{0};
  int written = 0;
  const int window = 2 * args.threads;
  std::vector<std::thread> workers;
  for (int w = 0; w < args.threads; ++w) {
    workers.emplace_back([&] {
      for (int k = next++; k < frames; k = next++) {
        {
          std::unique_lock<std::mutex> lock(mutex);
          room.wait(lock, [&] { return k < written + window; });
        }
        SampleFrame frame = scene.Render(times[k]);
        std::lock_guard<std::mutex> lock(mutex);
        done.emplace(k, std::move(frame));
        ready.notify_all();
      }
    });
  }

  const double tf_step = 1.0 / (3.0 * args.rate);
  int tf_index = 0;
  size_t complete_tags = 0;
  double max_blur = 0, min_light = 1e9, max_light = 0;
  for (int k = 0; k < frames; ++k) {
    SampleFrame frame;
    {
      std::unique_lock<std::mutex> lock(mutex);
      ready.wait(lock, [&] { return done.count(k) > 0; });
      frame = std::move(done.at(k));
      done.erase(k);
    }
    for (; args.start + tf_index * tf_step <= times[k] + 1e-9; ++tf_index) {
      const double t = args.start + tf_index * tf_step;
      tf2_msgs::TFMessage odom;
      odom.transforms.push_back(ToTransform(scene.RoverPose(t), kOdom, kBase, Stamp(t)));
      bag.write("/tf", Stamp(t), odom);
    }
    std_msgs::Header optical;
    optical.seq = k;
    optical.stamp = Stamp(times[k]);
    optical.frame_id = kOptical;
    std_msgs::Header body = optical;
    body.frame_id = kBody;
    bag.write(kImageTopic, optical.stamp, ImageFor(frame.image, optical));
    bag.write(kInfoTopic, optical.stamp, CameraInfoFor(scene, optical));
    bag.write(kCloudTopic, optical.stamp, CloudFor(frame.cloud, body));
    bag.write(kTruthTopic, optical.stamp, TruthFor(frame, optical));
    for (const auto& tag : frame.truth) complete_tags += tag.complete;
    max_blur = std::max(max_blur, frame.motion_blur_px);
    min_light = std::min(min_light, frame.brightness);
    max_light = std::max(max_light, frame.brightness);
    {
      std::lock_guard<std::mutex> lock(mutex);
      written = k + 1;
    }
    room.notify_all();
  }
  for (auto& w : workers) w.join();
  bag.close();
  std::filesystem::rename(args.output + ".active", args.output);

  const double seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - started).count();
  std::printf("make_sample_bag: %s: %d frames (%.2f-%.2f s at %.3g Hz), %zu whole markers, brightness %.2f-%.2f, "
              "motion blur up to %.1f px, %.0f MB in %.1f s\n",
              args.output.c_str(), frames, times.front(), times.back(), args.rate, complete_tags, min_light, max_light,
              max_blur, std::filesystem::file_size(args.output) / 1e6, seconds);
  return 0;
}

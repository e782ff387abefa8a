// make_sample_bag: writes the sample recording that `make demo`, the replay tests and the rviz
// screenshot use. A rover's stereo camera approaches and passes a URC post (id 1 on three faces)
// with five more DICT_4X4_50 markers at 2-15 m; light, exposure and motion blur change over time.
//
//   make_sample_bag [--output sample.bag] [--start 0] [--duration 15] [--rate 15] [--threads N]
//                   [--supersample 4] [--jpeg-quality 80] [--compression lz4|bz2|none] [--summary]
//
// Recorded like a field bag of a ZED-style driver (what launch/rover.launch expects), no raw images:
//   /zed/left/image_rect_color/compressed  sensor_msgs/CompressedImage, jpeg of the bgr8 1280x720 image
//                                          ("bgr8; jpeg compressed bgr8", as image_transport's compressed
//                                          plugin writes it), frame zed_left_camera_optical_frame
//   /zed/left/camera_info                  sensor_msgs/CameraInfo (rectified, no distortion) from the
//                                          driver's own 2 Hz timer, stamped when sent: never an image's stamp
//   /zed/point_cloud/cloud_registered      sensor_msgs/PointCloud2 for every third image (a stereo cloud is
//                                          slower), organized 640x360 (one point per 2x2 pixel block)
//                                          with a ZED 2's depth error (sim::DepthNoise::Zed2: range-squared
//                                          patchy noise, fattened edges, holes on featureless patches),
//                                          float32 x y z + 4 bytes padding (point_step 16, like a ZED's
//                                          XYZRGBA), frame zed_left_camera_frame, stamped with its image's stamp
//   /tf                                    odom -> base_link at 3x the frame rate
//   /tf_static (latched)                   base_link -> zed_left_camera_frame -> ..._optical_frame, odom -> truth_<marker>
//   /truth/tags                            arucotag/ArucoTagTruth, one per image, same stamp
// Every frame is a function of its time only: the output is identical byte for byte on every run,
// and a --start/--duration excerpt holds the same frames (and clouds, and camera_info stamps) as
// the full recording.
#include <arucotag/ros/messages.hpp>  // first: renames the generated ArucoTag message
#include <arucotag/ArucoTagTruth.h>

#include <algorithm>
#include <atomic>
#include <chrono>
#include <condition_variable>
#include <cstdio>
#include <filesystem>
#include <iostream>
#include <functional>
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
#include <opencv2/imgcodecs.hpp>
#include <sensor_msgs/CompressedImage.h>
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
const char* const kImageTopic = "/zed/left/image_rect_color/compressed";
const char* const kInfoTopic = "/zed/left/camera_info";
const char* const kCloudTopic = "/zed/point_cloud/cloud_registered";
const char* const kTruthTopic = "/truth/tags";

// camera_info timing: the driver sends it from its own timer at 2 Hz, 43 ms out of phase with the
// images at scene time 0, stamped with the time it is sent. So its stamp is never an image's, and
// the latest camera_info when an image arrives is 0-0.5 s older than the image (images do not wait
// for one; a detector must keep the latest rather than synchronize). The schedule is on scene time,
// so an excerpt holds the same stamps; its first camera_info is the last one sent before its first
// image, so the camera is known from the first frame on.
constexpr double kInfoPeriod = 0.5;  // s
constexpr double kInfoPhase = 0.043;  // s
// One cloud per kCloudEvery images: the frames whose index on the recording's grid (scene time x
// rate, so excerpts agree) is a multiple of it.
constexpr int kCloudEvery = 3;
// A stereo driver publishes the cloud after its image (it is computed from the pair), but a replay
// must not depend on which of two topics reaches the detector's callback queue first: a second
// replay has to give the same output. So each cloud goes into the bag 2.5 image periods BEFORE its
// image (just after the image three before it, the previous cloud's). With a cloud on every third
// image, no image is more than one period from its nearest cloud, so the first image that can pair
// with cloud c (the detector takes the nearest within cloud_max_dt) is image c - 1; the cloud is
// played 1.5 periods (100 ms at 15 Hz) before that image, so it is queued first. Images before
// c - 1 are nearer to the previous cloud, which the detector still holds.
constexpr double kCloudLeadPeriods = 2.5;

struct Args {
  std::string output = "sample.bag";
  double start = 0.0, duration = 15.0, rate = 15.0;
  int threads = static_cast<int>(std::max(1u, std::thread::hardware_concurrency()));
  int supersample = 4;
  int jpeg_quality = 80;  // image_transport's compressed plugin default
  std::string compression = "lz4";
  bool summary = false;
};

void Usage() {
  std::cerr << "usage: make_sample_bag [--output FILE] [--start S] [--duration S] [--rate HZ] [--threads N]\n"
               "                       [--supersample N] [--jpeg-quality Q] [--compression lz4|bz2|none] [--summary]\n"
               "  Writes the sample recording (defaults: sample.bag, 0-15 s at 15 Hz, jpeg quality 80, lz4 chunks).\n"
               "  --start/--duration/--rate cut an excerpt with the same frames; --summary prints what each marker\n"
               "  shows and writes nothing.\n";
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
    else if (arg == "--jpeg-quality") args.jpeg_quality = std::stoi(value());
    else if (arg == "--compression") args.compression = value();
    else if (arg == "--summary") args.summary = true;
    else if (arg == "--help" || arg == "-h") throw std::runtime_error("");
    else throw std::runtime_error("unknown argument " + arg);
  }
  if (!(args.start >= 0) || !(args.duration > 0) || !(args.rate > 0) || args.threads < 1 || args.supersample < 1 ||
      args.jpeg_quality < 1 || args.jpeg_quality > 100)
    throw std::runtime_error("need --start >= 0, --duration > 0, --rate > 0, --threads >= 1, --supersample >= 1, "
                             "--jpeg-quality 1-100");
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

sensor_msgs::CompressedImage CompressedFor(std::vector<uint8_t> jpeg, const std_msgs::Header& header) {
  sensor_msgs::CompressedImage image;
  image.header = header;
  image.format = "bgr8; jpeg compressed bgr8";
  image.data = std::move(jpeg);
  return image;
}

// x y z as float32, then 4 bytes where a ZED puts its packed colour (zero here): point_step 16.
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
  cloud.point_step = 16;
  cloud.row_step = cloud.point_step * cloud.width;
  cloud.is_dense = false;  // NaN holes
  cv::Mat padded(xyz.size(), CV_32FC4, cv::Scalar::all(0));
  const int from_to[] = {0, 0, 1, 1, 2, 2};
  cv::mixChannels(&xyz, 1, &padded, 1, from_to, 3);
  cloud.data = PackedRows(padded);
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

  const double period = 1.0 / args.rate;
  const auto frame_index = [&](double t) { return std::llround(t * args.rate); };  // on the recording's grid
  const auto has_cloud = [&](int k) { return frame_index(times[k]) % kCloudEvery == 0; };
  const double cloud_lead = kCloudLeadPeriods * period;
  // camera_info schedule: the last send at or before the first image, then every kInfoPeriod.
  auto info_index = static_cast<long long>(std::floor((times.front() - kInfoPhase) / kInfoPeriod));
  const auto info_time = [](long long n) { return kInfoPhase + n * kInfoPeriod; };

  // Messages wait here until nothing later can come before them, so the bag is written in time
  // order (clouds are due before their images; out-of-order chunks would make playback slower).
  std::multimap<ros::Time, std::function<void()>> queue;
  const auto flush_before = [&](const ros::Time& until) {
    while (!queue.empty() && queue.begin()->first < until) {
      queue.begin()->second();
      queue.erase(queue.begin());
    }
  };

  // Static frames first, at the bag's first instant (a cloud of the first frame, or the first
  // camera_info, can come before the first image).
  double first_due = info_time(info_index);
  for (int k = 0; k < frames && times[k] - cloud_lead < first_due; ++k) {
    if (has_cloud(k)) first_due = times[k] - cloud_lead;
  }
  const ros::Time begin = Stamp(first_due);
  tf2_msgs::TFMessage statics;
  statics.transforms.push_back(ToTransform(SampleScene::MastMount(), kBase, kBody, begin));
  statics.transforms.push_back(ToTransform(SampleScene::OpticalInBody(), kBody, kOptical, begin));
  for (const auto& m : scene.Markers()) statics.transforms.push_back(ToTransform(m.pose, kOdom, "truth_" + m.name, begin));
  bag.write("/tf_static", begin, statics, LatchedHeader<tf2_msgs::TFMessage>());

  // Frames render and encode on worker threads (each frame is independent) and are queued in time
  // order, with the odometry TF (3 per frame, one at each image stamp) and camera_info interleaved.
  struct Rendered {
    SampleFrame frame;
    std::vector<uint8_t> jpeg;
  };
  cv::setNumThreads(args.threads > 1 ? 1 : -1);  // parallel across frames, not inside one
  std::mutex mutex;
  std::condition_variable ready, room;
  std::map<int, Rendered> done;
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
        Rendered r{scene.Render(times[k], has_cloud(k)), {}};
        cv::imencode(".jpg", r.frame.image, r.jpeg, {cv::IMWRITE_JPEG_QUALITY, args.jpeg_quality});
        std::lock_guard<std::mutex> lock(mutex);
        done.emplace(k, std::move(r));
        ready.notify_all();
      }
    });
  }

  const double tf_step = 1.0 / (3.0 * args.rate);
  int tf_index = 0;
  size_t complete_tags = 0, image_bytes = 0, clouds = 0, infos = 0;
  double max_blur = 0, min_light = 1e9, max_light = 0;
  for (int k = 0; k < frames; ++k) {
    Rendered rendered;
    {
      std::unique_lock<std::mutex> lock(mutex);
      ready.wait(lock, [&] { return done.count(k) > 0; });
      rendered = std::move(done.at(k));
      done.erase(k);
    }
    const SampleFrame& frame = rendered.frame;
    for (; args.start + tf_index * tf_step <= times[k] + 1e-9; ++tf_index) {
      const double t = args.start + tf_index * tf_step;
      tf2_msgs::TFMessage odom;
      odom.transforms.push_back(ToTransform(scene.RoverPose(t), kOdom, kBase, Stamp(t)));
      queue.emplace(Stamp(t), [&bag, odom, t] { bag.write("/tf", Stamp(t), odom); });
    }
    for (; info_time(info_index) <= times[k]; ++info_index, ++infos) {
      std_msgs::Header header;
      header.seq = static_cast<uint32_t>(infos);
      header.stamp = Stamp(info_time(info_index));
      header.frame_id = kOptical;
      queue.emplace(header.stamp, [&bag, info = CameraInfoFor(scene, header)] { bag.write(kInfoTopic, info.header.stamp, info); });
    }
    std_msgs::Header optical;
    optical.seq = k;
    optical.stamp = Stamp(times[k]);
    optical.frame_id = kOptical;
    image_bytes += rendered.jpeg.size();
    queue.emplace(optical.stamp, [&bag, image = CompressedFor(std::move(rendered.jpeg), optical)] {
      bag.write(kImageTopic, image.header.stamp, image);
    });
    queue.emplace(optical.stamp, [&bag, truth = TruthFor(frame, optical)] { bag.write(kTruthTopic, truth.header.stamp, truth); });
    if (!frame.cloud.empty()) {
      std_msgs::Header body = optical;
      body.seq = static_cast<uint32_t>(clouds++);
      body.frame_id = kBody;
      const ros::Time due = Stamp(times[k] - cloud_lead);
      queue.emplace(due, [&bag, due, cloud = CloudFor(frame.cloud, body)] { bag.write(kCloudTopic, due, cloud); });
    }
    for (const auto& tag : frame.truth) complete_tags += tag.complete;
    max_blur = std::max(max_blur, frame.motion_blur_px);
    min_light = std::min(min_light, frame.brightness);
    max_light = std::max(max_light, frame.brightness);
    // Whatever a later frame queues is at or after its cloud's time.
    if (k + 1 < frames) flush_before(Stamp(times[k + 1] - cloud_lead));
    {
      std::lock_guard<std::mutex> lock(mutex);
      written = k + 1;
    }
    room.notify_all();
  }
  flush_before(ros::TIME_MAX);
  for (auto& w : workers) w.join();
  bag.close();
  std::filesystem::rename(args.output + ".active", args.output);

  const double seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - started).count();
  std::printf("make_sample_bag: %s: %d frames (%.2f-%.2f s at %.3g Hz, jpeg %.0f kB each), %zu clouds, %zu camera_info, "
              "%zu whole markers, brightness %.2f-%.2f, motion blur up to %.1f px, %.0f MB in %.1f s\n",
              args.output.c_str(), frames, times.front(), times.back(), args.rate, image_bytes / 1e3 / frames, clouds,
              infos, complete_tags, min_light, max_light, max_blur, std::filesystem::file_size(args.output) / 1e6,
              seconds);
  return 0;
}

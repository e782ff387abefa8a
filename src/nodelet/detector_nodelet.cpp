// The detector nodelet: subscribes image (+ camera_info, + points), runs the arucotag core, publishes
// tags, tracks, bundles, TF, overlay, markers and diagnostics. Conversions live in conversions.cpp, parameters in
// parameters.cpp; this file is wiring. Every callback runs on the nodelet's single-threaded queue,
// except the connect callbacks (publisher threads), which only touch the subscriptions.
//
// Input model: real drivers stamp camera_info apart from the image, send one frame, repeat or zero
// stamps and send clouds slower than images, and bags loop. So nothing is synchronized: each image
// is processed as it arrives, with the latest camera_info and the cached cloud nearest in stamp
// (within ~cloud_max_dt; PnP alone otherwise). Only before the first camera_info ever comes do
// images wait for it (~camera_info_wait). With ~output_frame, images pass a tf2_ros::MessageFilter
// first, so the callback never blocks on TF and a frame goes out in output_frame or not at all.
#include <arucotag/ros/conversions.hpp>  // first: it renames the generated ArucoTag message
#include <arucotag/ros/image_input.hpp>
#include <arucotag/ros/parameters.hpp>
#include <arucotag/ros/tracks.hpp>

#include <algorithm>
#include <atomic>
#include <chrono>
#include <condition_variable>
#include <deque>
#include <map>
#include <memory>
#include <mutex>
#include <optional>
#include <thread>

#include <diagnostic_updater/diagnostic_updater.h>
#include <dynamic_reconfigure/server.h>
#include <image_transport/image_transport.h>
#include <message_filters/cache.h>
#include <nodelet/nodelet.h>
#include <pluginlib/class_list_macros.hpp>
#include <tf2_ros/buffer.h>
#include <tf2_ros/message_filter.h>
#include <tf2_ros/transform_broadcaster.h>
#include <tf2_ros/transform_listener.h>

#include <arucotag/arucotag.hpp>

#if defined(__GLIBC__)
#include <malloc.h>
#endif

namespace arucotag {

namespace {

using sensor_msgs::CameraInfo;
using sensor_msgs::CameraInfoConstPtr;
using sensor_msgs::CompressedImageConstPtr;
using sensor_msgs::Image;
using sensor_msgs::ImageConstPtr;
using sensor_msgs::PointCloud2;
using sensor_msgs::PointCloud2ConstPtr;
using Transport = NodeletParameters::Transport;
using Cloud = pcl::PointCloud<pcl::PointXYZ>;

constexpr double kThrottle = 5.0;        // s between repeats of one kind of warning or error
constexpr size_t kStatsWindow = 100;     // frames behind the rates and times in diagnostics
constexpr double kRecentError = 10.0;    // s an error keeps the diagnostic status at WARN
constexpr double kReleasePeriod = 1.0;   // s between returns of freed memory to the OS (glibc)

using Clock = std::chrono::steady_clock;

double Ms(Clock::duration d) { return std::chrono::duration<double, std::milli>(d).count(); }

const char* FailureName(tf2_ros::FilterFailureReason reason) {
  switch (reason) {
    case tf2_ros::filter_failure_reasons::OutTheBack:
      return "older than the TF buffer";
    case tf2_ros::filter_failure_reasons::EmptyFrameID:
      return "the image has no frame_id";
    default:
      return "no transform came before newer images filled the queue (~queue_size)";
  }
}

// A quantile of a small window (copies: diagnostics run once a second).
double Quantile(std::deque<double> values, double q) {
  if (values.empty()) return 0.0;
  const size_t k = std::min(values.size() - 1, static_cast<size_t>(q * (values.size() - 1) + 0.5));
  std::nth_element(values.begin(), values.begin() + k, values.end());
  return values[k];
}

// Every frame frees a 15 MB cloud and a 2.7 MB image (roscpp's receive buffers, the messages, the
// cloud as a cv::Mat), often on another thread than the one that allocated them. glibc raises its mmap
// threshold to the largest chunk freed (up to 32 MB), so from the first frame on these live in its
// per-thread arenas, and the arenas keep what is freed: the manager's RSS climbs to the high-water mark
// of the frames ever in flight at once and stays there (make soak: +40 MB between minutes 1 and 3 of a
// quiet run; under load, 180 MB of the arenas' 266 MB free but resident). Not a leak, but a manager
// that never gives back its worst moment. This hands the free pages back to the OS once a period, on
// a thread of its own so no callback waits for it (a trim holds one arena lock at a time: 13 ms mean
// per second with the 2 cores overloaded).
class MemoryReleaser {
 public:
  explicit MemoryReleaser(double period) {
#if defined(__GLIBC__)
    thread_ = std::thread([this, period] {
      std::unique_lock<std::mutex> lock(mutex_);
      while (!stop_.wait_for(lock, std::chrono::duration<double>(period), [this] { return stopping_; })) {
        malloc_trim(0);
      }
    });
#else
    (void)period;  // other allocators return large blocks themselves
#endif
  }
  ~MemoryReleaser() {
    {
      std::lock_guard<std::mutex> lock(mutex_);
      stopping_ = true;
    }
    stop_.notify_one();
    if (thread_.joinable()) thread_.join();
  }

 private:
  std::mutex mutex_;
  std::condition_variable stop_;
  bool stopping_ = false;
  std::thread thread_;
};

// malloc_trim is process-wide: one releaser for all the detectors in a manager.
std::shared_ptr<MemoryReleaser> SharedMemoryReleaser() {
  static std::mutex mutex;
  static std::weak_ptr<MemoryReleaser> shared;
  std::lock_guard<std::mutex> lock(mutex);
  std::shared_ptr<MemoryReleaser> releaser = shared.lock();
  if (!releaser) {
    releaser = std::make_shared<MemoryReleaser>(kReleasePeriod);
    shared = releaser;
  }
  return releaser;
}

}  // namespace

class DetectorNodelet : public nodelet::Nodelet {
 public:
  ~DetectorNodelet() override;

 private:
  void onInit() override;
  void Start();
  void ConnectCallback();
  void Subscribe();
  void Unsubscribe();

  void OnImage(const ImageConstPtr& image);
  void OnCompressed(const CompressedImageConstPtr& compressed);
  void Admit(const ImageConstPtr& image, Transport from);
  void CheckStamp(const ros::Time& stamp);
  void KeepTransport(Transport from);
  void OnInfo(const CameraInfoConstPtr& info);
  void OnCloud(const PointCloud2ConstPtr& cloud);
  void StopWaitingForInfo();
  void Route(const ImageConstPtr& image);
  void OnTfFailure(const ImageConstPtr& image, tf2_ros::FilterFailureReason reason);

  void Process(const ImageConstPtr& image);
  std::optional<CameraModel> CameraFor(const ros::Time& stamp, const cv::Size& size);
  PointCloud2ConstPtr NearestCloud(const ros::Time& stamp) const;
  const Cloud& CloudFor(const PointCloud2ConstPtr& cloud, const std_msgs::Header& image_header, const cv::Size& size);
  void Measure(ArucoTag& tag, const std::optional<CameraModel>& camera, const Cloud& cloud);
  TagTracks UpdateTracks(const std::vector<ArucoTag>& tags, const std_msgs::Header& header,
                         const std::optional<geometry_msgs::TransformStamped>& to_output);
  // What follows the tags (Process publishes those first): the tracks, TF and the views.
  void Publish(const ImageConstPtr& image, const ArucoTagArray& array, const std::vector<ArucoTag>& tags,
               const TagTracks& tracks);
  void PublishTf(const ArucoTagArray& array, const TagTracks& tracks);
  void PublishBundles(const std_msgs::Header& header, const CameraModel& camera, const std::vector<ArucoTag>& tags,
                      const geometry_msgs::TransformStamped* to_output);
  std::string ChildFramePrefix(const std::string& camera_frame) const;

  void OnReconfigure(ArucotagDetectorConfig& config, uint32_t level);
  void Diagnose(diagnostic_updater::DiagnosticStatusWrapper& status);
  // Throttled per kind (`key`), so a second, different problem is never hidden behind the first.
  void Warn(const std::string& key, const std::string& what);
  void Fail(const std::string& key, const std::string& what);
  bool Due(const std::string& key);

  NodeletParameters params_;
  std::unique_ptr<Detector> detector_;
  std::unique_ptr<TagTracker> tracker_;
  std::map<uint32_t, ros::Time> last_seen_;  // per track id: the exact stamp of its last hit
  std::string inert_reason_;  // set when the parameters were rejected: nothing is subscribed

  ros::NodeHandle nh_, pnh_;
  std::unique_ptr<image_transport::ImageTransport> it_;

  // Inputs.
  std::mutex connect_mutex_;
  std::atomic<bool> subscribed_{false};
  bool shutting_down_ = false;
  image_transport::Subscriber image_sub_;
  ros::Subscriber compressed_sub_, info_sub_, cloud_sub_;
  std::atomic<bool> reset_inputs_{true};
  Transport reading_ = Transport::kAuto;  // with ~image_transport auto: the transport chosen so far (connect_mutex_)
  ros::Time last_image_stamp_;
  CameraInfoConstPtr latest_info_;
  std::unique_ptr<message_filters::Cache<PointCloud2>> clouds_;
  std::deque<ImageConstPtr> waiting_for_info_;
  bool info_wait_over_ = false;
  ros::WallTimer info_wait_timer_;
  std::unique_ptr<tf2_ros::MessageFilter<Image>> tf_filter_;  // images waiting for ~output_frame
  std::map<const Image*, Clock::time_point> arrived_;          // arrival of images not yet processed

  // Outputs.
  ros::Publisher tags_pub_, markers_pub_, tracks_pub_, track_markers_pub_, bundles_pub_, bundle_markers_pub_;
  image_transport::Publisher overlay_pub_;
  std::unique_ptr<tf2_ros::TransformBroadcaster> tf_broadcaster_;
  std::unique_ptr<tf2_ros::Buffer> tf_buffer_;
  std::unique_ptr<tf2_ros::TransformListener> tf_listener_;
  std::map<std::string, ros::Time> last_tf_stamp_;  // per child frame: TF never gets one stamp twice
  Cloud cloud_;  // the frame's cloud (CloudFor): its 15 MB buffer is reused frame after frame

  boost::recursive_mutex reconfigure_mutex_;
  std::unique_ptr<dynamic_reconfigure::Server<ArucotagDetectorConfig>> reconfigure_;

  // Diagnostics.
  std::unique_ptr<diagnostic_updater::Updater> updater_;
  ros::Timer diagnostics_timer_;

  std::shared_ptr<MemoryReleaser> releaser_;
  struct Counts {
    size_t received = 0, processed = 0, skipped = 0, with_cloud = 0, without_cloud = 0, tf_dropped = 0;
    size_t waited_for_info = 0, without_info = 0, infos = 0, clouds = 0, stale_info = 0;
    size_t zero_stamps = 0, repeated_stamps = 0, time_jumps = 0, tf_repeats = 0;
    size_t no_frame_id = 0, bad_clouds = 0, clouds_without_depth = 0, reconfigure_rejected = 0;
  } counts_;
  std::deque<Clock::time_point> arrivals_;
  std::deque<double> processing_ms_, latency_ms_;
  std::map<std::string, ros::WallTime> last_report_;
  std::string last_error_, last_warning_;
  Clock::time_point last_error_time_;
};

DetectorNodelet::~DetectorNodelet() {
  {
    std::lock_guard<std::mutex> lock(connect_mutex_);
    shutting_down_ = true;
  }
  diagnostics_timer_.stop();
  info_wait_timer_.stop();
  reconfigure_.reset();
  Unsubscribe();
  tf_filter_.reset();
}

void DetectorNodelet::onInit() {
  nh_ = getNodeHandle();
  pnh_ = getPrivateNodeHandle();
  // A throw out of onInit would take the loading request down with it and, for the standalone
  // node, the process: report, stay inert, leave the manager and its other nodelets alone.
  try {
    updater_ = std::make_unique<diagnostic_updater::Updater>(nh_, pnh_, getName());
    updater_->setHardwareID("arucotag");
    updater_->add("detector", this, &DetectorNodelet::Diagnose);
    diagnostics_timer_ = nh_.createTimer(ros::Duration(1.0), [this](const ros::TimerEvent&) { updater_->update(); });
  } catch (const std::exception& e) {
    NODELET_ERROR("cannot start diagnostics: %s", e.what());
  }
  try {
    Start();
  } catch (const std::exception& e) {
    std::lock_guard<std::mutex> lock(connect_mutex_);
    inert_reason_ = e.what();
    NODELET_ERROR("%s; this nodelet stays inert (nothing subscribed or published) until it is reloaded with valid "
                  "parameters",
                  e.what());
    Unsubscribe();
  }
}

void DetectorNodelet::Start() {
  params_ = ReadParameters(pnh_);
  detector_ = std::make_unique<Detector>(params_.detector);
  tracker_ = std::make_unique<TagTracker>(params_.tracker);
  for (const auto& name : UnknownParameters(pnh_)) {
    NODELET_WARN("unknown parameter ~%s is ignored (typo?); config/detector.yaml lists the valid ones", name.c_str());
  }

  if (params_.use_point_cloud || !params_.output_frame.empty()) {
    tf_buffer_ = std::make_unique<tf2_ros::Buffer>();
    tf_listener_ = std::make_unique<tf2_ros::TransformListener>(*tf_buffer_);
  }
  if (!params_.output_frame.empty()) {
    tf_filter_ = std::make_unique<tf2_ros::MessageFilter<Image>>(*tf_buffer_, params_.output_frame,
                                                                 static_cast<uint32_t>(params_.queue_size), nh_);
    tf_filter_->registerCallback(&DetectorNodelet::Process, this);
    tf_filter_->registerFailureCallback(
        [this](const ImageConstPtr& image, tf2_ros::FilterFailureReason reason) { OnTfFailure(image, reason); });
  }
  if (params_.publish_tf) tf_broadcaster_ = std::make_unique<tf2_ros::TransformBroadcaster>();
  releaser_ = SharedMemoryReleaser();
  clouds_ = std::make_unique<message_filters::Cache<PointCloud2>>(static_cast<unsigned>(params_.cloud_cache_size));

  reconfigure_ = std::make_unique<dynamic_reconfigure::Server<ArucotagDetectorConfig>>(reconfigure_mutex_, pnh_);
  // Show the values in use (the server would otherwise clamp to the cfg ranges without a word).
  ArucotagDetectorConfig in_use = ToReconfigure(params_.detector, params_.preprocess);
  TrackToReconfigure(params_.tracker, params_.tf_from_validated_tracks, in_use);
  reconfigure_->updateConfig(in_use);
  reconfigure_->setCallback([this](ArucotagDetectorConfig& config, uint32_t level) { OnReconfigure(config, level); });

  it_ = std::make_unique<image_transport::ImageTransport>(nh_);
  // Hold the lock across advertise so a connect callback never sees a half-made publisher.
  std::lock_guard<std::mutex> lock(connect_mutex_);
  const auto connect = [this](const ros::SingleSubscriberPublisher&) { ConnectCallback(); };
  const auto connect_image = [this](const image_transport::SingleSubscriberPublisher&) { ConnectCallback(); };
  tags_pub_ = nh_.advertise<ArucoTagArray>("tags", 10, connect, connect);
  markers_pub_ = nh_.advertise<visualization_msgs::MarkerArray>("markers", 1, connect, connect);
  tracks_pub_ = nh_.advertise<TagTracks>("tracks", 10, connect, connect);
  track_markers_pub_ = nh_.advertise<visualization_msgs::MarkerArray>("track_markers", 1, connect, connect);
  overlay_pub_ = it_->advertise("overlay", 1, connect_image, connect_image);
  if (!params_.bundles.empty()) {
    bundles_pub_ = nh_.advertise<BundleArray>("bundles", 10, connect, connect);
    bundle_markers_pub_ = nh_.advertise<visualization_msgs::MarkerArray>("bundle_markers", 1, connect, connect);
  }
  if (params_.publish_tf) Subscribe();  // TF has no subscriber count: it always counts as listening
  const char* transport = params_.transport == Transport::kRaw          ? "raw"
                          : params_.transport == Transport::kCompressed ? "compressed"
                                                                        : "raw or compressed, whichever comes first";
  NODELET_INFO("detecting %s markers on %s (%s)%s%s%s%s", params_.detector.dictionary.c_str(),
               nh_.resolveName("image").c_str(), transport, params_.use_point_cloud ? " with points from " : "",
               params_.use_point_cloud ? nh_.resolveName("points").c_str() : "",
               params_.output_frame.empty() ? "" : ", poses in ", params_.output_frame.c_str());
  if (!params_.bundles.empty()) {
    NODELET_INFO("%zu marker bundles (~bundles), published on %s", params_.bundles.size(),
                 nh_.resolveName("bundles").c_str());
  }
}

void DetectorNodelet::ConnectCallback() {
  std::lock_guard<std::mutex> lock(connect_mutex_);
  if (shutting_down_ || !inert_reason_.empty()) return;
  const bool listening = params_.publish_tf || tags_pub_.getNumSubscribers() > 0 ||
                         markers_pub_.getNumSubscribers() > 0 || overlay_pub_.getNumSubscribers() > 0 ||
                         tracks_pub_.getNumSubscribers() > 0 || track_markers_pub_.getNumSubscribers() > 0 ||
                         bundles_pub_.getNumSubscribers() > 0 || bundle_markers_pub_.getNumSubscribers() > 0;
  if (listening && !subscribed_) {
    Subscribe();
  } else if (!listening && subscribed_) {
    Unsubscribe();
  }
}

// Callers hold connect_mutex_ (or run before any publisher exists).
void DetectorNodelet::Subscribe() {
  const uint32_t q = static_cast<uint32_t>(params_.queue_size);
  if (params_.transport != Transport::kCompressed) {
    image_sub_ = it_->subscribe("image", q, &DetectorNodelet::OnImage, this, image_transport::TransportHints("raw"));
  }
  if (params_.transport != Transport::kRaw) {
    // No compressed_image_transport on Debian: take the plugin's topic and decode here.
    compressed_sub_ = nh_.subscribe(nh_.resolveName("image") + "/compressed", q, &DetectorNodelet::OnCompressed, this);
  }
  reading_ = Transport::kAuto;  // a fresh subscription chooses its transport again
  info_sub_ = nh_.subscribe("camera_info", q, &DetectorNodelet::OnInfo, this);
  if (params_.use_point_cloud) cloud_sub_ = nh_.subscribe("points", q, &DetectorNodelet::OnCloud, this);
  reset_inputs_ = true;
  subscribed_ = true;
}

void DetectorNodelet::Unsubscribe() {
  image_sub_.shutdown();
  compressed_sub_.shutdown();
  info_sub_.shutdown();
  cloud_sub_.shutdown();
  subscribed_ = false;
}

void DetectorNodelet::OnCompressed(const CompressedImageConstPtr& compressed) {
  sensor_msgs::ImagePtr image;
  try {
    image = DecodeCompressedImage(*compressed);
  } catch (const std::exception& e) {
    ++counts_.received;
    ++counts_.skipped;
    Fail("decode", std::string("frame skipped: ") + e.what());
    return;
  }
  Admit(image, Transport::kCompressed);
}

void DetectorNodelet::OnImage(const ImageConstPtr& image) { Admit(image, Transport::kRaw); }

void DetectorNodelet::Admit(const ImageConstPtr& image, Transport from) {
  const auto now = Clock::now();
  ++counts_.received;
  arrivals_.push_back(now);
  if (arrivals_.size() > kStatsWindow) arrivals_.pop_front();
  if (params_.transport == Transport::kAuto) KeepTransport(from);
  CheckStamp(image->header.stamp);
  arrived_[image.get()] = now;

  if (!latest_info_ && !info_wait_over_ && params_.camera_info_wait > 0.0) {
    // Drivers and bags often send camera_info after the first image: a single-frame bag would
    // otherwise never get a pose. Once any camera_info has come (or the wait is over) nothing waits.
    if (waiting_for_info_.empty()) {
      info_wait_timer_ = nh_.createWallTimer(
          ros::WallDuration(params_.camera_info_wait), [this](const ros::WallTimerEvent&) { StopWaitingForInfo(); },
          true);
    }
    ++counts_.waited_for_info;
    waiting_for_info_.push_back(image);
    if (waiting_for_info_.size() >= static_cast<size_t>(params_.queue_size)) StopWaitingForInfo();
    return;
  }
  Route(image);
}

void DetectorNodelet::CheckStamp(const ros::Time& stamp) {
  if (reset_inputs_.exchange(false)) {
    last_image_stamp_ = stamp;
    return;
  }
  if (stamp.isZero()) {
    ++counts_.zero_stamps;
    Warn("zero stamp", "image stamp is zero (a driver without a clock?): tags keep stamp 0, TF is stamped with the "
                       "time of arrival, and only clouds stamped within ~cloud_max_dt of 0 pair with it");
  } else if (stamp < last_image_stamp_) {
    ++counts_.time_jumps;
    Warn("time jump", "image stamps went back " + std::to_string((last_image_stamp_ - stamp).toSec()) +
                          " s (a looping bag or a restarted driver): cached clouds and TF history dropped, "
                          "the latest camera_info kept");
    clouds_ = std::make_unique<message_filters::Cache<PointCloud2>>(static_cast<unsigned>(params_.cloud_cache_size));
    last_tf_stamp_.clear();
  } else if (stamp == last_image_stamp_) {
    ++counts_.repeated_stamps;
    Warn("repeated stamp", "image stamp " + std::to_string(stamp.toSec()) +
                               " repeats the previous image's: tags are published again, TF once per stamp");
  }
  last_image_stamp_ = stamp;
}

void DetectorNodelet::KeepTransport(Transport from) {
  std::lock_guard<std::mutex> lock(connect_mutex_);
  if (!subscribed_ || reading_ == from) return;
  const std::string topic = nh_.resolveName("image");
  if (from == Transport::kRaw) {
    compressed_sub_.shutdown();
    NODELET_INFO("reading raw images from %s (%s/compressed dropped)", topic.c_str(), topic.c_str());
  } else {
    image_sub_.shutdown();
    NODELET_INFO("reading compressed images from %s/compressed (raw %s dropped)", topic.c_str(), topic.c_str());
  }
  reading_ = from;
}

void DetectorNodelet::OnInfo(const CameraInfoConstPtr& info) {
  latest_info_ = info;
  ++counts_.infos;
  if (!waiting_for_info_.empty()) StopWaitingForInfo();
}

void DetectorNodelet::OnCloud(const PointCloud2ConstPtr& cloud) {
  ++counts_.clouds;
  clouds_->add(cloud);
}

void DetectorNodelet::StopWaitingForInfo() {
  info_wait_timer_.stop();
  if (!latest_info_) {
    info_wait_over_ = true;
    Warn("no camera_info", "no camera_info on " + nh_.resolveName("camera_info") + " after " +
                               std::to_string(params_.camera_info_wait) +
                               " s (~camera_info_wait): publishing ids and corners without poses until one comes");
  }
  std::deque<ImageConstPtr> images;
  images.swap(waiting_for_info_);
  for (const auto& image : images) Route(image);
}

void DetectorNodelet::Route(const ImageConstPtr& image) {
  if (tf_filter_) {
    tf_filter_->add(image);  // Process runs once output_frame's transform at the image stamp is known
  } else {
    Process(image);
  }
}

void DetectorNodelet::OnTfFailure(const ImageConstPtr& image, tf2_ros::FilterFailureReason reason) {
  arrived_.erase(image.get());
  ++counts_.tf_dropped;
  Warn(std::string("tf ") + FailureName(reason),
       "frame dropped: no transform " + params_.output_frame + " <- '" + image->header.frame_id + "' at " +
           std::to_string(image->header.stamp.toSec()) + ": " + FailureName(reason));
}

void DetectorNodelet::Process(const ImageConstPtr& image) {
  const auto start = Clock::now();
  const auto arrival = arrived_.find(image.get());
  const Clock::time_point arrived = arrival == arrived_.end() ? start : arrival->second;
  if (arrival != arrived_.end()) arrived_.erase(arrival);
  const std_msgs::Header& header = image->header;

  DetectorImage input;
  std::vector<ArucoTag> tags;
  std::optional<CameraModel> camera;
  try {
    input = DetectorImageFrom(image);
    PreprocessOptions options = params_.preprocess;
    options.format = input.format;
    cv::Mat grey;
    PreprocessFrame(input.pixels, grey, options);
    // A raw image's lens bends marker edges; Detect then leaves the markers it bends to the edge fit
    // (the pattern fit's model has straight edges). A rectified image's model has no distortion.
    camera = CameraFor(header.stamp, input.pixels.size());
    tags = camera ? Detect(grey, *detector_, *camera) : Detect(grey, *detector_);
  } catch (const std::exception& e) {  // arucotag::Error, cv::Exception
    ++counts_.skipped;
    Fail("image " + image->encoding, std::string("frame skipped: ") + e.what());
    return;
  }
  if (header.frame_id.empty()) {
    ++counts_.no_frame_id;
    Fail("no frame_id", "image has no frame_id: its tags go out without a frame and no TF (set the driver's frame_id)");
  }
  std::optional<geometry_msgs::TransformStamped> to_output;
  if (!params_.output_frame.empty() && params_.output_frame != header.frame_id) {
    try {
      // The MessageFilter let the image through, so the transform is there: no waiting.
      to_output = tf_buffer_->lookupTransform(params_.output_frame, header.frame_id, header.stamp);
    } catch (const tf2::TransformException& e) {
      ++counts_.tf_dropped;
      Warn("tf lookup", "frame dropped: no transform " + params_.output_frame + " <- " + header.frame_id + ": " +
                            e.what());
      return;
    }
  }

  const cv::Size size = input.pixels.size();
  const Cloud& points = CloudFor(params_.use_point_cloud ? NearestCloud(header.stamp) : nullptr, header, size);
  if (params_.use_point_cloud) ++(points.empty() ? counts_.without_cloud : counts_.with_cloud);
  for (auto& tag : tags) Measure(tag, camera, points);
  if (!points.empty() && !tags.empty() &&
      std::none_of(tags.begin(), tags.end(), [](const ArucoTag& tag) { return tag.cloud.valid; })) {
    ++counts_.clouds_without_depth;
    Warn("cloud without depth", "the point cloud has too few finite points on every tag (NaN or inf there: no "
                                "depth, or the cloud is all NaN): poses from PnP alone");
  }
  // The tags go out first, before the tracker's update, TF and the views: they are what the rover's
  // stack waits for (bench_nodelet on 640x480 frames: the tracker's update was 0.03 ms of each frame's
  // latency with 5 markers, 0.2 ms with 50). Published as a shared pointer and only read after that.
  const auto array =
      boost::make_shared<const ArucoTagArray>(ToMessage(tags, header, to_output ? &*to_output : nullptr));
  tags_pub_.publish(array);
  Publish(image, *array, tags, UpdateTracks(tags, header, to_output));
  if (camera && !params_.bundles.empty()) PublishBundles(header, *camera, tags, to_output ? &*to_output : nullptr);

  ++counts_.processed;
  const auto end = Clock::now();
  processing_ms_.push_back(Ms(end - start));
  latency_ms_.push_back(Ms(end - arrived));
  if (processing_ms_.size() > kStatsWindow) processing_ms_.pop_front();
  if (latency_ms_.size() > kStatsWindow) latency_ms_.pop_front();
}

std::optional<CameraModel> DetectorNodelet::CameraFor(const ros::Time& stamp, const cv::Size& size) {
  if (!latest_info_) {
    ++counts_.without_info;
    return std::nullopt;
  }
  const double age = std::abs((stamp - latest_info_->header.stamp).toSec());
  if (params_.camera_info_max_age > 0.0 && age > params_.camera_info_max_age) {
    ++counts_.stale_info;
    Warn("stale camera_info", "camera_info is stamped " + std::to_string(age) +
                                  " s away from the image (~camera_info_max_age " +
                                  std::to_string(params_.camera_info_max_age) + " s): using it anyway");
  }
  try {
    CameraModel camera = CameraModelFromInfo(*latest_info_, params_.rectified, size);
    camera.corner_noise = params_.corner_noise;
    return camera;
  } catch (const std::exception& e) {
    ++counts_.without_info;
    Fail("camera_info", std::string("no poses: ") + e.what());
    return std::nullopt;
  }
}

PointCloud2ConstPtr DetectorNodelet::NearestCloud(const ros::Time& stamp) const {
  const ros::Duration max_dt(params_.cloud_max_dt);
  const ros::Time from = stamp.toSec() > max_dt.toSec() ? stamp - max_dt : ros::Time();
  PointCloud2ConstPtr nearest;
  double best = params_.cloud_max_dt;
  for (const auto& cloud : clouds_->getInterval(from, stamp + max_dt)) {
    const double dt = std::abs((cloud->header.stamp - stamp).toSec());
    if (dt <= best) {  // on a tie the newer cloud (later in the cache) wins
      best = dt;
      nearest = cloud;
    }
  }
  return nearest;
}

// The frame's cloud in cloud_ (one buffer for the nodelet's life: frames are processed one at a time),
// empty when there is none to use.
const Cloud& DetectorNodelet::CloudFor(const PointCloud2ConstPtr& cloud, const std_msgs::Header& image_header,
                                       const cv::Size& size) {
  cloud_.clear();
  if (!cloud || params_.pose_source == PoseSource::kPnp) return cloud_;
  try {
    std::optional<geometry_msgs::TransformStamped> to_image;
    if (!cloud->header.frame_id.empty() && cloud->header.frame_id != image_header.frame_id) {
      // Stereo drivers publish the cloud in a body frame; the core wants it in the image's. No
      // waiting: the transform is usually static, and a frame without its cloud still gets PnP.
      to_image = tf_buffer_->lookupTransform(image_header.frame_id, cloud->header.frame_id, cloud->header.stamp);
    }
    CloudFromMessage(*cloud, size, to_image ? &to_image->transform : nullptr, cloud_);
    return cloud_;
  } catch (const tf2::TransformException& e) {
    Warn("cloud tf", "point cloud not used (PnP alone): no transform " + image_header.frame_id + " <- " +
                         cloud->header.frame_id + " at the cloud's stamp: " + e.what());
  } catch (const std::exception& e) {
    ++counts_.bad_clouds;
    Fail("cloud", std::string("point cloud not used (PnP alone): ") + e.what());
  }
  cloud_.clear();
  return cloud_;
}

void DetectorNodelet::Measure(ArucoTag& tag, const std::optional<CameraModel>& camera, const Cloud& cloud) {
  try {
    if (camera) EstimatePoseFromPNP(*camera, tag);
    if (!cloud.empty()) EstimatePoseFromPointCloud(cloud, tag, params_.cloud);
  } catch (const std::exception& e) {
    Fail("pose", "tag " + std::to_string(tag.id) + ": " + e.what());
  }
  ResolvePose(tag, params_.pose_source);
}

// Without ~output_frame the tracker gets the camera's own poses (TrackerConfig::filter is off).
TagTracks DetectorNodelet::UpdateTracks(const std::vector<ArucoTag>& tags, const std_msgs::Header& header,
                                        const std::optional<geometry_msgs::TransformStamped>& to_output) {
  cv::Matx33d rotation = cv::Matx33d::eye();
  cv::Vec3d translation(0.0, 0.0, 0.0);
  if (to_output) ToRigid(to_output->transform, rotation, translation);
  tracker_->Update(header.frame_id, header.stamp.toSec(), MeasurementsInFrame(tags, rotation, translation));
  std_msgs::Header frame = header;
  if (!params_.output_frame.empty()) frame.frame_id = params_.output_frame;
  return ToMessage(*tracker_, frame, header.stamp, last_seen_);
}

void DetectorNodelet::Publish(const ImageConstPtr& image, const ArucoTagArray& array,
                              const std::vector<ArucoTag>& tags, const TagTracks& tracks) {
  tracks_pub_.publish(boost::make_shared<TagTracks>(tracks));
  if (params_.publish_tf) PublishTf(array, tracks);
  if (markers_pub_.getNumSubscribers() > 0) markers_pub_.publish(ToMarkers(array));
  if (track_markers_pub_.getNumSubscribers() > 0) track_markers_pub_.publish(ToTrackMarkers(tracks));
  if (overlay_pub_.getNumSubscribers() > 0) {
    try {
      cv::Mat overlay = OverlayBgr8(image);
      DrawDetections(overlay, tags);
      overlay_pub_.publish(ToImageMessage(overlay, "bgr8", image->header));
    } catch (const std::exception& e) {
      Fail("overlay", std::string("overlay: ") + e.what());
    }
  }
}

std::string DetectorNodelet::ChildFramePrefix(const std::string& camera_frame) const {
  if (!params_.frame_prefix.empty()) return params_.frame_prefix;
  // tf2 refuses frame ids with a leading slash (tf1 style); keep the name, drop the slash.
  const size_t begin = camera_frame.find_first_not_of('/');
  return begin == std::string::npos ? std::string() : camera_frame.substr(begin) + "/aruco_";
}

void DetectorNodelet::PublishTf(const ArucoTagArray& array, const TagTracks& tracks) {
  if (array.header.frame_id.empty()) return;  // Process reported it
  // A post shows one id on several faces; TF gets only the best-measured face per id, or with
  // ~tf_from_validated_tracks the most-seen validated track per id (its filtered pose).
  std::map<int, geometry_msgs::Pose> best;
  if (params_.tf_from_validated_tracks) {
    best = ValidatedPoses(tracks);
  } else {
    std::map<int, const ArucoTagMsg*> chosen;
    for (const auto& tag : array.tags) {
      if (tag.pose_source == ArucoTagMsg::NONE) continue;
      const ArucoTagMsg*& current = chosen[tag.id];
      if (!current || BetterMeasured(tag, *current)) current = &tag;
    }
    for (const auto& [id, tag] : chosen) best[id] = tag->pose;
  }
  std_msgs::Header header = array.header;
  if (header.stamp.isZero()) header.stamp = ros::Time::now();
  const std::string prefix = ChildFramePrefix(array.header.frame_id);
  std::vector<geometry_msgs::TransformStamped> transforms;
  for (const auto& [id, pose] : best) {
    const std::string child = prefix + std::to_string(id);
    ros::Time& last = last_tf_stamp_[child];
    if (last == header.stamp) {  // a repeated image stamp: listeners would reject it as TF_REPEATED_DATA
      ++counts_.tf_repeats;
      continue;
    }
    last = header.stamp;
    transforms.push_back(ToTransform(pose, header, child));
  }
  if (!transforms.empty()) tf_broadcaster_->sendTransform(transforms);
}

void DetectorNodelet::PublishBundles(const std_msgs::Header& header, const CameraModel& camera,
                                     const std::vector<ArucoTag>& tags,
                                     const geometry_msgs::TransformStamped* to_output) {
  std::vector<BundlePose> poses;
  std::vector<std::string> children;
  // Like the tags' default frames, one set per camera: <camera frame_id>/<bundle frame>.
  const size_t begin = header.frame_id.find_first_not_of('/');
  const std::string camera_frame = begin == std::string::npos ? std::string() : header.frame_id.substr(begin);
  for (const auto& bundle : params_.bundles) {
    try {
      poses.push_back(EstimateBundlePose(camera, bundle, tags));
    } catch (const std::exception& e) {
      Fail("bundle " + bundle.name, "bundle '" + bundle.name + "': " + e.what());
      poses.emplace_back();
    }
    children.push_back(camera_frame + "/" + bundle.frame);
  }
  const BundleArray array = ToMessage(poses, children, header, to_output);
  bundles_pub_.publish(array);
  if (bundle_markers_pub_.getNumSubscribers() > 0) bundle_markers_pub_.publish(ToBundleMarkers(array, params_.bundles));
  if (!params_.publish_tf || array.header.frame_id.empty()) return;
  std_msgs::Header parent = array.header;
  if (parent.stamp.isZero()) parent.stamp = ros::Time::now();
  std::vector<geometry_msgs::TransformStamped> transforms;
  for (const auto& bundle : array.bundles) {
    ros::Time& last = last_tf_stamp_[bundle.child_frame_id];
    if (last == parent.stamp) {  // a repeated image stamp: listeners would reject it as TF_REPEATED_DATA
      ++counts_.tf_repeats;
      continue;
    }
    last = parent.stamp;
    transforms.push_back(ToTransform(bundle.pose.pose, parent, bundle.child_frame_id));
  }
  if (!transforms.empty()) tf_broadcaster_->sendTransform(transforms);
}

void DetectorNodelet::OnReconfigure(ArucotagDetectorConfig& config, uint32_t) {
  DetectorConfig detector = params_.detector;
  PreprocessOptions preprocess = params_.preprocess;
  try {
    ApplyReconfigure(config, detector, preprocess);
    TrackerConfig tracker = params_.tracker;
    bool tf_from_validated_tracks = params_.tf_from_validated_tracks;
    ApplyTrackReconfigure(config, tracker, tf_from_validated_tracks);
    auto fresh = std::make_unique<Detector>(detector);  // validates everything before anything changes
    detector_ = std::move(fresh);
    tracker_->SetConfig(tracker);
    params_.detector = detector;
    params_.preprocess = preprocess;
    params_.tracker = tracker;
    params_.tf_from_validated_tracks = tf_from_validated_tracks;
  } catch (const std::exception& e) {
    // Not throttled: each request is someone's deliberate action and deserves its answer.
    ++counts_.reconfigure_rejected;
    last_error_ = std::string("dynamic_reconfigure rejected: ") + e.what() + "; keeping the previous settings";
    last_error_time_ = Clock::now();
    NODELET_ERROR("%s", last_error_.c_str());
    config = ToReconfigure(params_.detector, params_.preprocess);  // report what is really in use
    TrackToReconfigure(params_.tracker, params_.tf_from_validated_tracks, config);
  }
}

bool DetectorNodelet::Due(const std::string& key) {
  const ros::WallTime now = ros::WallTime::now();
  auto it = last_report_.find(key);
  if (it != last_report_.end() && (now - it->second).toSec() < kThrottle) return false;
  last_report_[key] = now;
  return true;
}

void DetectorNodelet::Warn(const std::string& key, const std::string& what) {
  last_warning_ = what;
  if (Due(key)) NODELET_WARN("%s", what.c_str());
}

void DetectorNodelet::Fail(const std::string& key, const std::string& what) {
  last_error_ = what;
  last_error_time_ = Clock::now();
  if (Due(key)) NODELET_ERROR("%s", what.c_str());
}

void DetectorNodelet::Diagnose(diagnostic_updater::DiagnosticStatusWrapper& status) {
  using diagnostic_msgs::DiagnosticStatus;
  const auto now = Clock::now();
  double rate = 0.0;
  if (arrivals_.size() >= 2 && now - arrivals_.back() < std::chrono::seconds(2)) {
    rate = (arrivals_.size() - 1) / std::chrono::duration<double>(arrivals_.back() - arrivals_.front()).count();
  }
  double mean_ms = 0.0, max_ms = 0.0;
  for (double ms : processing_ms_) {
    mean_ms += ms / processing_ms_.size();
    max_ms = std::max(max_ms, ms);
  }
  const bool recent_error = !last_error_.empty() && now - last_error_time_ < std::chrono::duration<double>(kRecentError);
  if (!inert_reason_.empty()) {
    status.summary(DiagnosticStatus::ERROR, "inert: " + inert_reason_);
  } else if (recent_error) {
    status.summary(DiagnosticStatus::WARN, last_error_);
  } else if (!subscribed_) {
    status.summary(DiagnosticStatus::OK, "idle: nobody listens");
  } else if (counts_.received > 0 && !latest_info_) {
    status.summary(DiagnosticStatus::WARN, "no camera_info on " + nh_.resolveName("camera_info") +
                                               ": ids and corners without poses");
  } else {
    status.summary(DiagnosticStatus::OK, "ok");
  }
  const Counts& c = counts_;
  status.add("input rate (Hz)", rate);
  status.add("processing time mean (ms)", mean_ms);
  status.add("processing time max (ms)", max_ms);
  status.add("latency from arrival median (ms)", Quantile(latency_ms_, 0.5));
  status.add("latency from arrival p99 (ms)", Quantile(latency_ms_, 0.99));
  status.add("frames received", c.received);
  status.add("frames processed", c.processed);
  status.add("frames skipped (bad input)", c.skipped);
  status.add("frames dropped (no output_frame transform)", c.tf_dropped);
  status.add("frames with a cloud", c.with_cloud);
  status.add("frames without a cloud", c.without_cloud);
  status.add("frames without camera_info", c.without_info);
  status.add("frames held for the first camera_info", c.waited_for_info);
  status.add("camera_info received", c.infos);
  status.add("camera_info stale (> ~camera_info_max_age)", c.stale_info);
  status.add("point clouds received", c.clouds);
  status.add("zero stamps", c.zero_stamps);
  status.add("repeated stamps", c.repeated_stamps);
  status.add("stamps going back (loops)", c.time_jumps);
  status.add("TF not resent for a repeated stamp", c.tf_repeats);
  status.add("frames without frame_id", c.no_frame_id);
  status.add("frames whose cloud was rejected (bad input)", c.bad_clouds);
  status.add("frames whose cloud has no depth on any tag", c.clouds_without_depth);
  status.add("reconfigure requests rejected", c.reconfigure_rejected);
  status.add("last error", last_error_.empty() ? "none" : last_error_);
  status.add("last warning", last_warning_.empty() ? "none" : last_warning_);
}

}  // namespace arucotag

PLUGINLIB_EXPORT_CLASS(arucotag::DetectorNodelet, nodelet::Nodelet)

// The detector nodelet: subscribes image (+ camera_info, + points), runs the arucotag core, publishes
// tags, TF, overlay, markers and diagnostics. Conversions live in conversions.cpp, parameters in
// parameters.cpp; this file is wiring. Every callback runs on the nodelet's single-threaded queue,
// except the connect callbacks (publisher threads), which only touch the subscriptions.
#include <arucotag/ros/conversions.hpp>  // first: it renames the generated ArucoTag message
#include <arucotag/ros/parameters.hpp>

#include <atomic>
#include <chrono>
#include <deque>
#include <map>
#include <memory>
#include <mutex>
#include <optional>

#include <diagnostic_updater/diagnostic_updater.h>
#include <dynamic_reconfigure/server.h>
#include <image_transport/image_transport.h>
#include <message_filters/pass_through.h>
#include <message_filters/subscriber.h>
#include <message_filters/sync_policies/approximate_time.h>
#include <message_filters/sync_policies/exact_time.h>
#include <message_filters/synchronizer.h>
#include <nodelet/nodelet.h>
#include <pluginlib/class_list_macros.hpp>
#include <tf2_ros/buffer.h>
#include <tf2_ros/transform_broadcaster.h>
#include <tf2_ros/transform_listener.h>

#include <arucotag/arucotag.hpp>

namespace arucotag {

namespace {

using sensor_msgs::CameraInfo;
using sensor_msgs::CameraInfoConstPtr;
using sensor_msgs::CompressedImageConstPtr;
using sensor_msgs::Image;
using sensor_msgs::ImageConstPtr;
using sensor_msgs::PointCloud2;
using sensor_msgs::PointCloud2ConstPtr;
namespace policies = message_filters::sync_policies;

constexpr double kThrottle = 5.0;        // s between repeats of one warning or error
constexpr size_t kStatsWindow = 100;     // frames behind the rates and times in diagnostics
constexpr double kRecentError = 10.0;    // s an error keeps the diagnostic status at WARN

using Clock = std::chrono::steady_clock;

// Synchronizers of different arity and policy behind one owner; the callback is a member function.
template <class Policy, class Owner, class Callback, class... Filters>
std::shared_ptr<void> MakeSynchronizer(int queue_size, Owner* owner, Callback callback, Filters&... filters) {
  auto sync = std::make_shared<message_filters::Synchronizer<Policy>>(Policy(queue_size), filters...);
  sync->registerCallback(callback, owner);
  return sync;
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
  void OnInfo(const CameraInfoConstPtr& info);
  void OnCloud(const PointCloud2ConstPtr& cloud);
  void OnSynced(const ImageConstPtr& image, const CameraInfoConstPtr& info, const PointCloud2ConstPtr& cloud);
  void OnSyncedNoCloud(const ImageConstPtr& image, const CameraInfoConstPtr& info);
  std::string FallbackReason() const;

  void Process(const ImageConstPtr& image, const CameraInfoConstPtr& info, const PointCloud2ConstPtr& cloud);
  std::optional<CameraModel> CameraFor(const CameraInfoConstPtr& info, const cv::Size& size);
  cv::Mat CloudFor(const PointCloud2ConstPtr& cloud, const std_msgs::Header& image_header, const cv::Size& size);
  void Measure(ArucoTag& tag, const std::optional<CameraModel>& camera, const cv::Mat& cloud, const cv::Size& size);
  void Publish(const std_msgs::Header& header, const ImageView& view, const std::vector<ArucoTag>& tags);
  void PublishTf(const ArucoTagArray& array);

  void OnReconfigure(ArucotagDetectorConfig& config, uint32_t level);
  void Diagnose(diagnostic_updater::DiagnosticStatusWrapper& status);
  void Fail(const std::string& what);

  NodeletParameters params_;
  std::unique_ptr<Detector> detector_;
  std::string inert_reason_;  // set when the parameters were rejected: nothing is subscribed

  ros::NodeHandle nh_, pnh_;
  std::unique_ptr<image_transport::ImageTransport> it_;

  // Inputs. The synchronizer reads images from image_filter_, which raw and decoded compressed
  // images both feed, so one synchronizer serves both transports.
  std::mutex connect_mutex_;
  std::atomic<bool> subscribed_{false};
  bool shutting_down_ = false;
  image_transport::Subscriber image_sub_;
  ros::Subscriber compressed_sub_;
  message_filters::PassThrough<Image> image_filter_;
  message_filters::Subscriber<CameraInfo> info_sub_;
  message_filters::Subscriber<PointCloud2> cloud_sub_;
  std::shared_ptr<void> sync_;  // declared after the filters it holds connections to

  // Fallback when the synchronizer is silent (no camera_info, no cloud, stamps that never match).
  std::atomic<bool> reset_inputs_{true};
  ros::Time waiting_since_, last_synced_, last_image_stamp_, last_processed_;
  ImageConstPtr pending_;  // newest image the synchronizer has not matched yet, while falling back
  CameraInfoConstPtr latest_info_;
  size_t info_count_ = 0, cloud_count_ = 0;
  bool falling_back_ = false;

  // Outputs.
  ros::Publisher tags_pub_, markers_pub_;
  image_transport::Publisher overlay_pub_;
  std::unique_ptr<tf2_ros::TransformBroadcaster> tf_broadcaster_;
  std::unique_ptr<tf2_ros::Buffer> tf_buffer_;
  std::unique_ptr<tf2_ros::TransformListener> tf_listener_;

  boost::recursive_mutex reconfigure_mutex_;
  std::unique_ptr<dynamic_reconfigure::Server<ArucotagDetectorConfig>> reconfigure_;

  // Diagnostics.
  std::unique_ptr<diagnostic_updater::Updater> updater_;
  ros::Timer diagnostics_timer_;
  size_t received_ = 0, processed_ = 0, skipped_ = 0;
  std::deque<Clock::time_point> arrivals_;
  std::deque<double> processing_ms_;
  std::string last_error_;
  Clock::time_point last_error_time_;
};

DetectorNodelet::~DetectorNodelet() {
  {
    std::lock_guard<std::mutex> lock(connect_mutex_);
    shutting_down_ = true;
  }
  diagnostics_timer_.stop();
  reconfigure_.reset();
  Unsubscribe();
  sync_.reset();
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
  for (const auto& name : UnknownParameters(pnh_)) {
    NODELET_WARN("unknown parameter ~%s is ignored (typo?); config/detector.yaml lists the valid ones", name.c_str());
  }

  if (params_.use_point_cloud || !params_.output_frame.empty()) {
    tf_buffer_ = std::make_unique<tf2_ros::Buffer>();
    tf_listener_ = std::make_unique<tf2_ros::TransformListener>(*tf_buffer_);
  }
  if (params_.publish_tf) tf_broadcaster_ = std::make_unique<tf2_ros::TransformBroadcaster>();

  const int q = params_.queue_size;
  if (params_.use_point_cloud) {
    using Approximate = policies::ApproximateTime<Image, CameraInfo, PointCloud2>;
    using Exact = policies::ExactTime<Image, CameraInfo, PointCloud2>;
    sync_ = params_.approximate_sync
                ? MakeSynchronizer<Approximate>(q, this, &DetectorNodelet::OnSynced, image_filter_, info_sub_, cloud_sub_)
                : MakeSynchronizer<Exact>(q, this, &DetectorNodelet::OnSynced, image_filter_, info_sub_, cloud_sub_);
  } else {
    using Approximate = policies::ApproximateTime<Image, CameraInfo>;
    using Exact = policies::ExactTime<Image, CameraInfo>;
    sync_ = params_.approximate_sync
                ? MakeSynchronizer<Approximate>(q, this, &DetectorNodelet::OnSyncedNoCloud, image_filter_, info_sub_)
                : MakeSynchronizer<Exact>(q, this, &DetectorNodelet::OnSyncedNoCloud, image_filter_, info_sub_);
  }
  info_sub_.registerCallback(&DetectorNodelet::OnInfo, this);
  cloud_sub_.registerCallback(&DetectorNodelet::OnCloud, this);

  reconfigure_ = std::make_unique<dynamic_reconfigure::Server<ArucotagDetectorConfig>>(reconfigure_mutex_, pnh_);
  // Show the values in use (the server would otherwise clamp to the cfg ranges without a word).
  reconfigure_->updateConfig(ToReconfigure(params_.detector, params_.preprocess));
  reconfigure_->setCallback([this](ArucotagDetectorConfig& config, uint32_t level) { OnReconfigure(config, level); });

  it_ = std::make_unique<image_transport::ImageTransport>(nh_);
  // Hold the lock across advertise so a connect callback never sees a half-made publisher.
  std::lock_guard<std::mutex> lock(connect_mutex_);
  const auto connect = [this](const ros::SingleSubscriberPublisher&) { ConnectCallback(); };
  const auto connect_image = [this](const image_transport::SingleSubscriberPublisher&) { ConnectCallback(); };
  tags_pub_ = nh_.advertise<ArucoTagArray>("tags", 10, connect, connect);
  markers_pub_ = nh_.advertise<visualization_msgs::MarkerArray>("markers", 1, connect, connect);
  overlay_pub_ = it_->advertise("overlay", 1, connect_image, connect_image);
  if (params_.publish_tf) Subscribe();  // TF has no subscriber count: it always counts as listening
  NODELET_INFO("detecting %s markers on %s (%s)%s%s", params_.detector.dictionary.c_str(),
               nh_.resolveName("image").c_str(), params_.compressed ? "compressed" : "raw",
               params_.use_point_cloud ? " with points from " : "",
               params_.use_point_cloud ? nh_.resolveName("points").c_str() : "");
}

void DetectorNodelet::ConnectCallback() {
  std::lock_guard<std::mutex> lock(connect_mutex_);
  if (shutting_down_ || !inert_reason_.empty()) return;
  const bool listening = params_.publish_tf || tags_pub_.getNumSubscribers() > 0 ||
                         markers_pub_.getNumSubscribers() > 0 || overlay_pub_.getNumSubscribers() > 0;
  if (listening && !subscribed_) {
    Subscribe();
  } else if (!listening && subscribed_) {
    Unsubscribe();
  }
}

// Callers hold connect_mutex_ (or run before any publisher exists).
void DetectorNodelet::Subscribe() {
  const uint32_t q = static_cast<uint32_t>(params_.queue_size);
  if (params_.compressed) {
    // No compressed_image_transport on Debian: take the plugin's topic and decode here.
    compressed_sub_ = nh_.subscribe(nh_.resolveName("image") + "/compressed", q, &DetectorNodelet::OnCompressed, this);
  } else {
    image_sub_ = it_->subscribe("image", q, &DetectorNodelet::OnImage, this, image_transport::TransportHints("raw"));
  }
  info_sub_.subscribe(nh_, "camera_info", q);
  if (params_.use_point_cloud) cloud_sub_.subscribe(nh_, "points", q);
  reset_inputs_ = true;
  subscribed_ = true;
}

void DetectorNodelet::Unsubscribe() {
  image_sub_.shutdown();
  compressed_sub_.shutdown();
  info_sub_.unsubscribe();
  cloud_sub_.unsubscribe();
  subscribed_ = false;
}

void DetectorNodelet::OnCompressed(const CompressedImageConstPtr& compressed) {
  sensor_msgs::ImagePtr image;
  try {
    image = DecodeCompressed(*compressed);
  } catch (const std::exception& e) {
    ++received_;
    ++skipped_;
    Fail(std::string("frame skipped: ") + e.what());
    return;
  }
  OnImage(image);
}

void DetectorNodelet::OnImage(const ImageConstPtr& image) {
  ++received_;
  arrivals_.push_back(Clock::now());
  if (arrivals_.size() > kStatsWindow) arrivals_.pop_front();

  const ros::Time stamp = image->header.stamp;
  // After (re)subscribing, and when time runs backwards (a bag restarted), start afresh.
  if (reset_inputs_.exchange(false) || stamp < last_image_stamp_) {
    waiting_since_ = stamp;
    last_synced_ = last_processed_ = ros::Time();
    info_count_ = cloud_count_ = 0;
    pending_.reset();
  }
  last_image_stamp_ = stamp;
  image_filter_.add(image);  // OnSynced runs from here when this image completes a set

  const ros::Time since = last_synced_.isZero() ? waiting_since_ : last_synced_;
  if ((stamp - since).toSec() < params_.input_timeout) {
    falling_back_ = false;
    pending_.reset();
    return;
  }
  // The synchronizer has been silent for a while: never stall, use what there is. The image waits
  // one frame first, because its cloud or camera_info may still be on the way (clouds are big).
  falling_back_ = true;
  const ImageConstPtr previous = pending_;
  pending_ = image;
  if (previous && previous->header.stamp < stamp) {
    NODELET_WARN_THROTTLE(kThrottle, "%s", FallbackReason().c_str());
    Process(previous, latest_info_, nullptr);
  }
}

std::string DetectorNodelet::FallbackReason() const {
  if (info_count_ == 0) {
    return "no camera_info on " + nh_.resolveName("camera_info") +
           ": publishing ids and corners without poses (pose_source NONE)";
  }
  if (params_.use_point_cloud && cloud_count_ == 0) {
    return "no point cloud on " + nh_.resolveName("points") + ": poses from PnP only";
  }
  return std::string("image, camera_info") + (params_.use_point_cloud ? " and points" : "") +
         " do not synchronize (stamps too far apart" + (params_.approximate_sync ? "" : " for ~approximate_sync false") +
         "): using the latest camera_info without a cloud";
}

void DetectorNodelet::OnInfo(const CameraInfoConstPtr& info) {
  latest_info_ = info;
  ++info_count_;
}

void DetectorNodelet::OnCloud(const PointCloud2ConstPtr&) { ++cloud_count_; }

void DetectorNodelet::OnSynced(const ImageConstPtr& image, const CameraInfoConstPtr& info,
                               const PointCloud2ConstPtr& cloud) {
  last_synced_ = image->header.stamp;
  falling_back_ = false;
  if (pending_ && pending_->header.stamp <= last_synced_) pending_.reset();
  Process(image, info, cloud);
}

void DetectorNodelet::OnSyncedNoCloud(const ImageConstPtr& image, const CameraInfoConstPtr& info) {
  OnSynced(image, info, nullptr);
}

void DetectorNodelet::Process(const ImageConstPtr& image, const CameraInfoConstPtr& info,
                              const PointCloud2ConstPtr& cloud) {
  const ros::Time stamp = image->header.stamp;
  // The fallback and the synchronizer can both see one image; TF must not get it twice.
  if (!last_processed_.isZero() && stamp <= last_processed_) return;
  const auto start = Clock::now();

  ImageView view;
  std::vector<ArucoTag> tags;
  try {
    view = ViewImage(*image);
    PreprocessOptions options = params_.preprocess;
    options.format = view.format;
    cv::Mat grey;
    PreprocessFrame(view.pixels, grey, options);
    tags = Detect(grey, *detector_);
  } catch (const std::exception& e) {  // arucotag::Error, cv::Exception
    ++skipped_;
    Fail(std::string("frame skipped: ") + e.what());
    return;
  }
  last_processed_ = stamp;
  const cv::Size size = view.pixels.size();
  const std::optional<CameraModel> camera = CameraFor(info, size);
  const cv::Mat points = CloudFor(cloud, image->header, size);
  for (auto& tag : tags) Measure(tag, camera, points, size);
  Publish(image->header, view, tags);

  ++processed_;
  processing_ms_.push_back(std::chrono::duration<double, std::milli>(Clock::now() - start).count());
  if (processing_ms_.size() > kStatsWindow) processing_ms_.pop_front();
}

std::optional<CameraModel> DetectorNodelet::CameraFor(const CameraInfoConstPtr& info, const cv::Size& size) {
  if (!info) return std::nullopt;
  try {
    return CameraModelFromInfo(*info, params_.rectified, size);
  } catch (const std::exception& e) {
    Fail(std::string("no poses: ") + e.what());
    return std::nullopt;
  }
}

cv::Mat DetectorNodelet::CloudFor(const PointCloud2ConstPtr& cloud, const std_msgs::Header& image_header,
                                  const cv::Size& size) {
  if (!cloud || params_.pose_source == PoseSource::kPnp) return {};
  try {
    std::optional<geometry_msgs::TransformStamped> to_image;
    if (!cloud->header.frame_id.empty() && cloud->header.frame_id != image_header.frame_id) {
      // Stereo drivers publish the cloud in a body frame; the core wants it in the image's.
      to_image = tf_buffer_->lookupTransform(image_header.frame_id, cloud->header.frame_id, image_header.stamp,
                                             ros::Duration(params_.tf_timeout));
    }
    cv::Mat points = CloudToMat(*cloud, to_image ? &to_image->transform : nullptr);
    if (points.size() != size) {
      throw Error("point cloud is " + std::to_string(points.cols) + "x" + std::to_string(points.rows) +
                  " but the image is " + std::to_string(size.width) + "x" + std::to_string(size.height) +
                  "; an organized cloud must match the image pixel for pixel");
    }
    return points;
  } catch (const tf2::TransformException& e) {
    NODELET_WARN_THROTTLE(kThrottle, "point cloud not used (poses from PnP): no transform %s <- %s at the image stamp: %s",
                          image_header.frame_id.c_str(), cloud->header.frame_id.c_str(), e.what());
  } catch (const std::exception& e) {
    Fail(std::string("point cloud not used (poses from PnP): ") + e.what());
  }
  return {};
}

void DetectorNodelet::Measure(ArucoTag& tag, const std::optional<CameraModel>& camera, const cv::Mat& cloud,
                              const cv::Size& size) {
  try {
    if (camera) EstimatePoseFromPNP(*camera, tag);
    if (!cloud.empty()) EstimatePoseFromPointCloud(cloud, size, tag);
  } catch (const std::exception& e) {
    Fail("tag " + std::to_string(tag.id) + ": " + e.what());
  }
  ResolvePose(tag, params_.pose_source);
}

void DetectorNodelet::Publish(const std_msgs::Header& header, const ImageView& view,
                              const std::vector<ArucoTag>& tags) {
  std::optional<geometry_msgs::TransformStamped> to_output;
  if (!params_.output_frame.empty() && params_.output_frame != header.frame_id) {
    try {
      to_output = tf_buffer_->lookupTransform(params_.output_frame, header.frame_id, header.stamp,
                                              ros::Duration(params_.tf_timeout));
    } catch (const tf2::TransformException& e) {
      NODELET_WARN_THROTTLE(kThrottle, "poses stay in %s: no transform to ~output_frame %s at the image stamp: %s",
                            header.frame_id.c_str(), params_.output_frame.c_str(), e.what());
    }
  }
  const auto array = boost::make_shared<ArucoTagArray>(ToMessage(tags, header, to_output ? &*to_output : nullptr));
  tags_pub_.publish(array);
  if (params_.publish_tf) PublishTf(*array);
  if (markers_pub_.getNumSubscribers() > 0) markers_pub_.publish(ToMarkers(*array));
  if (overlay_pub_.getNumSubscribers() > 0) {
    try {
      cv::Mat overlay = ToBgrCopy(view);
      DrawDetections(overlay, tags);
      overlay_pub_.publish(ToImageMessage(overlay, "bgr8", header));
    } catch (const std::exception& e) {
      Fail(std::string("overlay: ") + e.what());
    }
  }
}

void DetectorNodelet::PublishTf(const ArucoTagArray& array) {
  if (array.header.frame_id.empty()) {
    NODELET_WARN_THROTTLE(kThrottle, "image has no frame_id: no TF published");
    return;
  }
  // A post shows one id on several faces; TF gets only the best-measured face per id.
  std::map<int, const ArucoTagMsg*> best;
  for (const auto& tag : array.tags) {
    if (tag.pose_source == ArucoTagMsg::NONE) continue;
    const ArucoTagMsg*& chosen = best[tag.id];
    if (!chosen || BetterMeasured(tag, *chosen)) chosen = &tag;
  }
  std::vector<geometry_msgs::TransformStamped> transforms;
  for (const auto& [id, tag] : best) {
    transforms.push_back(ToTransform(*tag, array.header, params_.frame_prefix + std::to_string(id)));
  }
  if (!transforms.empty()) tf_broadcaster_->sendTransform(transforms);
}

void DetectorNodelet::OnReconfigure(ArucotagDetectorConfig& config, uint32_t) {
  DetectorConfig detector = params_.detector;
  PreprocessOptions preprocess = params_.preprocess;
  try {
    ApplyReconfigure(config, detector, preprocess);
    auto fresh = std::make_unique<Detector>(detector);  // validates everything before anything changes
    detector_ = std::move(fresh);
    params_.detector = detector;
    params_.preprocess = preprocess;
  } catch (const std::exception& e) {
    NODELET_ERROR("dynamic_reconfigure rejected: %s; keeping the previous settings", e.what());
    config = ToReconfigure(params_.detector, params_.preprocess);  // report what is really in use
  }
}

void DetectorNodelet::Fail(const std::string& what) {
  NODELET_ERROR_THROTTLE(kThrottle, "%s", what.c_str());
  last_error_ = what;
  last_error_time_ = Clock::now();
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
  } else if (falling_back_) {
    status.summary(DiagnosticStatus::WARN, FallbackReason());
  } else if (!subscribed_) {
    status.summary(DiagnosticStatus::OK, "idle: nobody listens");
  } else {
    status.summary(DiagnosticStatus::OK, "ok");
  }
  status.add("input rate (Hz)", rate);
  status.add("processing time mean (ms)", mean_ms);
  status.add("processing time max (ms)", max_ms);
  status.add("frames received", received_);
  status.add("frames processed", processed_);
  status.add("frames dropped", received_ - std::min(received_, processed_));
  status.add("frames skipped (bad input)", skipped_);
  status.add("camera_info received", info_count_);
  status.add("point clouds received", cloud_count_);
  status.add("last error", last_error_.empty() ? "none" : last_error_);
}

}  // namespace arucotag

PLUGINLIB_EXPORT_CLASS(arucotag::DetectorNodelet, nodelet::Nodelet)

#include "rig.hpp"

#include <algorithm>
#include <cmath>
#include <cstring>

#include <opencv2/calib3d.hpp>
#include <opencv2/imgcodecs.hpp>
#include <sensor_msgs/PointField.h>
#include <sensor_msgs/image_encodings.h>
#include <tf2/LinearMath/Matrix3x3.h>
#include <tf2/LinearMath/Quaternion.h>

namespace arucotag::test {

cv::Matx33d BodyFromOpticalRotation() {
  // body x = optical z (forward), body y = -optical x (left), body z = -optical y (up).
  return cv::Matx33d(0, 0, 1, -1, 0, 0, 0, -1, 0);
}

cv::Vec3d BodyFromOpticalTranslation() { return {0.10, 0.06, 0.30}; }

geometry_msgs::TransformStamped BodyFromOpticalTf() {
  const cv::Matx33d r = BodyFromOpticalRotation();
  const cv::Vec3d t = BodyFromOpticalTranslation();
  tf2::Quaternion q;
  tf2::Matrix3x3(r(0, 0), r(0, 1), r(0, 2), r(1, 0), r(1, 1), r(1, 2), r(2, 0), r(2, 1), r(2, 2)).getRotation(q);
  geometry_msgs::TransformStamped tf;
  tf.header.frame_id = kBodyFrame;
  tf.child_frame_id = kOpticalFrame;
  tf.transform.translation.x = t[0];
  tf.transform.translation.y = t[1];
  tf.transform.translation.z = t[2];
  tf.transform.rotation.x = q.x();
  tf.transform.rotation.y = q.y();
  tf.transform.rotation.z = q.z();
  tf.transform.rotation.w = q.w();
  return tf;
}

sim::Camera TestCamera() { return sim::MakeCamera({640, 480}, 60.0); }

Scene Render(const std::vector<sim::Marker>& markers, const sim::RenderOptions& options,
             const sim::DepthNoise& stereo) {
  Scene scene;
  scene.camera = TestCamera();
  scene.markers = markers;
  cv::Mat depth;
  scene.image = sim::RenderScene(scene.camera, markers, options, &depth);
  // The cloud a stereo camera would give: range-squared patchy depth noise, fattened edges, no depth
  // on featureless patches (the render's flat paper and grey), seeded with the render.
  sim::CloudOptions cloud;
  cloud.stereo = stereo;
  cloud.seed = options.seed;
  scene.cloud = sim::MakeOrganizedCloud(scene.camera, depth, cloud, scene.image);
  return scene;
}

sim::Marker MainMarker() { return sim::FacingCamera(7, 0.15, {0.12, -0.08, 1.3}, 30.0, 10.0, 15.0); }

Rig::Rig(ros::NodeHandle& nh) : nh_(nh) {
  image_pub_ = nh_.advertise<sensor_msgs::Image>("/cam/image", 5);
  info_pub_ = nh_.advertise<sensor_msgs::CameraInfo>("/cam/camera_info", 5);
  cloud_pub_ = nh_.advertise<sensor_msgs::PointCloud2>("/cam/points", 5);
  body_cloud_pub_ = nh_.advertise<sensor_msgs::PointCloud2>("/cam/points_body", 5);
  compressed_pub_ = nh_.advertise<sensor_msgs::CompressedImage>("/cam/image/compressed", 5);
}

ros::Time Rig::Publish(const Scene& scene, const Channels& channels) {
  ros::Time stamp = ros::Time::now();
  if (stamp <= last_stamp_) stamp = last_stamp_ + ros::Duration(0, 1000);
  last_stamp_ = stamp;
  if (channels.info) info_pub_.publish(InfoMessage(scene.camera, stamp));
  if (channels.cloud) cloud_pub_.publish(CloudMessage(scene.cloud, stamp, kOpticalFrame));
  if (channels.body_cloud) {
    body_cloud_pub_.publish(CloudMessage(scene.cloud, stamp, kBodyFrame, BodyFromOpticalRotation(),
                                         BodyFromOpticalTranslation()));
  }
  // Each image is processed the moment it arrives with the clouds already there; a 5 MB cloud on
  // its own connection can overtake a small image, so give it a head start.
  if (channels.cloud || channels.body_cloud) ros::WallDuration(0.03).sleep();
  if (!channels.compressed.empty()) {
    sensor_msgs::CompressedImage compressed;
    compressed.header.stamp = stamp;
    compressed.header.frame_id = kOpticalFrame;
    compressed.format = "bgr8; " + channels.compressed.substr(1) + " compressed bgr8";
    const std::vector<int> quality{cv::IMWRITE_JPEG_QUALITY, 95};
    cv::imencode(channels.compressed, scene.image, compressed.data, quality);
    compressed_pub_.publish(compressed);
  }
  if (channels.image) image_pub_.publish(ImageMessage(scene.image, stamp));
  return stamp;
}

bool Rig::WaitForSubscribers(const std::vector<std::string>& topics, double timeout) {
  const std::map<std::string, const ros::Publisher*> known{{"/cam/image", &image_pub_},
                                                           {"/cam/camera_info", &info_pub_},
                                                           {"/cam/points", &cloud_pub_},
                                                           {"/cam/points_body", &body_cloud_pub_},
                                                           {"/cam/image/compressed", &compressed_pub_}};
  return WaitUntil(
      [&] {
        return std::all_of(topics.begin(), topics.end(),
                           [&](const std::string& topic) { return known.at(topic)->getNumSubscribers() > 0; });
      },
      timeout);
}

sensor_msgs::ImagePtr Rig::ImageMessage(const cv::Mat& bgr, const ros::Time& stamp) {
  auto msg = boost::make_shared<sensor_msgs::Image>();
  msg->header.stamp = stamp;
  msg->header.frame_id = kOpticalFrame;
  msg->width = bgr.cols;
  msg->height = bgr.rows;
  msg->encoding = bgr.channels() == 1 ? sensor_msgs::image_encodings::MONO8 : sensor_msgs::image_encodings::BGR8;
  msg->step = static_cast<uint32_t>(bgr.cols * bgr.elemSize());
  msg->data.resize(static_cast<size_t>(msg->step) * bgr.rows);
  bgr.copyTo(cv::Mat(bgr.rows, bgr.cols, bgr.type(), msg->data.data(), msg->step));
  return msg;
}

sensor_msgs::CameraInfoPtr Rig::InfoMessage(const sim::Camera& camera, const ros::Time& stamp) {
  auto info = boost::make_shared<sensor_msgs::CameraInfo>();
  info->header.stamp = stamp;
  info->header.frame_id = kOpticalFrame;
  info->width = camera.size.width;
  info->height = camera.size.height;
  // The render's own lens: plumb_bob (k1 k2 p1 p2 k3, missing ones zero), rational_polynomial past
  // five coefficients, equidistant for a fisheye.
  if (camera.fisheye) {
    info->distortion_model = "equidistant";
    info->D = camera.dist;
    info->D.resize(4, 0.0);
  } else if (camera.dist.size() > 5) {
    info->distortion_model = "rational_polynomial";
    info->D = camera.dist;
  } else {
    info->distortion_model = "plumb_bob";
    info->D = camera.dist;
    info->D.resize(5, 0.0);
  }
  for (int i = 0; i < 9; ++i) info->K[i] = camera.K.val[i];
  info->R = {1, 0, 0, 0, 1, 0, 0, 0, 1};
  for (int r = 0; r < 3; ++r)
    for (int c = 0; c < 3; ++c) info->P[r * 4 + c] = camera.K(r, c);
  return info;
}

sensor_msgs::PointCloud2Ptr Rig::CloudMessage(const cv::Mat& cloud, const ros::Time& stamp, const std::string& frame,
                                              const cv::Matx33d& rotation, const cv::Vec3d& translation) {
  auto msg = boost::make_shared<sensor_msgs::PointCloud2>();
  msg->header.stamp = stamp;
  msg->header.frame_id = frame;
  msg->height = cloud.rows;
  msg->width = cloud.cols;
  const char* names[] = {"x", "y", "z", "rgb"};
  for (int i = 0; i < 4; ++i) {
    sensor_msgs::PointField field;
    field.name = names[i];
    field.offset = 4 * i;
    field.datatype = sensor_msgs::PointField::FLOAT32;
    field.count = 1;
    msg->fields.push_back(field);
  }
  msg->point_step = 16;
  msg->row_step = msg->point_step * msg->width;
  msg->is_dense = false;
  msg->data.assign(static_cast<size_t>(msg->row_step) * msg->height, 0);
  const cv::Matx33f r = rotation;
  const cv::Vec3f t = translation;
  for (int v = 0; v < cloud.rows; ++v) {
    for (int u = 0; u < cloud.cols; ++u) {
      const cv::Vec3f p = r * cloud.at<cv::Vec3f>(v, u) + t;
      std::memcpy(&msg->data[static_cast<size_t>(v) * msg->row_step + u * msg->point_step], p.val, sizeof(p.val));
    }
  }
  return msg;
}

cv::Matx33d Rotation(const sim::Marker& marker) {
  cv::Matx33d r;
  cv::Rodrigues(marker.rvec, r);
  return r;
}

cv::Matx33d Rotation(const geometry_msgs::Quaternion& q) {
  const tf2::Matrix3x3 m(tf2::Quaternion(q.x, q.y, q.z, q.w));
  return cv::Matx33d(m[0][0], m[0][1], m[0][2], m[1][0], m[1][1], m[1][2], m[2][0], m[2][1], m[2][2]);
}

double AngleDeg(const cv::Matx33d& a, const cv::Matx33d& b) {
  const cv::Matx33d d = a * b.t();
  const double c = std::max(-1.0, std::min(1.0, (cv::trace(d) - 1.0) / 2.0));
  return std::acos(c) * 180.0 / CV_PI;
}

cv::Vec3d Position(const geometry_msgs::Point& p) { return {p.x, p.y, p.z}; }

::testing::AssertionResult PoseMatches(const geometry_msgs::Pose& pose, const cv::Matx33d& rotation,
                                       const cv::Vec3d& position, double range) {
  constexpr double kRangeFraction = 0.005, kDegrees = 1.0;
  const double error_m = cv::norm(Position(pose.position) - position);
  const double allowed_m = kRangeFraction * range;
  const double error_deg = AngleDeg(Rotation(pose.orientation), rotation);
  if (error_m <= allowed_m && error_deg <= kDegrees) {
    return ::testing::AssertionSuccess() << "position error " << error_m << " m, orientation error " << error_deg
                                         << " deg";
  }
  return ::testing::AssertionFailure() << "position error " << error_m << " m (allowed " << allowed_m
                                       << "), orientation error " << error_deg << " deg (allowed " << kDegrees
                                       << "); got " << Position(pose.position) << ", want " << position;
}

::testing::AssertionResult PoseMatches(const geometry_msgs::Pose& pose, const sim::Marker& truth) {
  return PoseMatches(pose, Rotation(truth), truth.tvec, cv::norm(truth.tvec));
}

::testing::AssertionResult CornersMatch(const arucotag::ArucoTag& tag, const sim::Camera& camera,
                                        const sim::Marker& truth, double max_px) {
  const auto expected = sim::ProjectCorners(camera, truth);
  double worst = 0.0;
  for (int i = 0; i < 4; ++i) {
    worst = std::max(worst, std::hypot(tag.corners[i].x - expected[i].x, tag.corners[i].y - expected[i].y));
  }
  if (worst <= max_px) return ::testing::AssertionSuccess();
  return ::testing::AssertionFailure() << "worst corner is " << worst << " px from the truth (allowed " << max_px << ")";
}

}  // namespace arucotag::test

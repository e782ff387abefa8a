#include <arucotag/ros/conversions.hpp>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <limits>

#include <boost/make_shared.hpp>
#include <image_geometry/pinhole_camera_model.h>
#include <opencv2/calib3d.hpp>
#include <opencv2/imgproc.hpp>
#include <pcl/common/transforms.h>
#include <pcl_conversions/pcl_conversions.h>
#include <sensor_msgs/PointField.h>
#include <sensor_msgs/distortion_models.h>
#include <sensor_msgs/image_encodings.h>
#include <tf2/LinearMath/Matrix3x3.h>
#include <tf2/LinearMath/Quaternion.h>
#include <tf2_geometry_msgs/tf2_geometry_msgs.h>

namespace arucotag {

namespace {

constexpr double kNan = std::numeric_limits<double>::quiet_NaN();
constexpr double kMarkerThickness = 0.005;  // m: flat enough to read as a sheet in rviz

geometry_msgs::Point ToPoint(const cv::Point2f& p) {
  geometry_msgs::Point point;
  point.x = p.x;
  point.y = p.y;
  return point;
}

std::string Size(long long width, long long height) { return std::to_string(width) + "x" + std::to_string(height); }

// A pose covariance moved into a frame rotated by q: position and the rotation angles (about fixed
// axes) both turn with the frame, so C' = B C B^T with B = diag(R, R). The translation adds nothing.
void RotateCovariance(const geometry_msgs::Quaternion& q, boost::array<double, 36>& covariance) {
  tf2::Quaternion rotation;
  tf2::fromMsg(q, rotation);
  const tf2::Matrix3x3 m(rotation);
  cv::Matx66d b = cv::Matx66d::zeros();
  for (int i = 0; i < 3; ++i) {
    for (int j = 0; j < 3; ++j) b(i, j) = b(3 + i, 3 + j) = m[i][j];
  }
  const cv::Matx66d moved = b * cv::Matx66d(covariance.data()) * b.t();
  std::copy(moved.val, moved.val + 36, covariance.begin());
}

std_msgs::ColorRGBA Rgba(float r, float g, float b, float a) {
  std_msgs::ColorRGBA color;
  color.r = r;
  color.g = g;
  color.b = b;
  color.a = a;
  return color;
}

// A printed marker in rviz: a flat CUBE, side x side x kMarkerThickness, at `pose`.
visualization_msgs::Marker Sheet(const std_msgs::Header& header, const char* ns, int id,
                                 const geometry_msgs::Pose& pose, double side, const std_msgs::ColorRGBA& color) {
  visualization_msgs::Marker sheet;
  sheet.header = header;
  sheet.ns = ns;
  sheet.id = id;
  sheet.type = visualization_msgs::Marker::CUBE;
  sheet.action = visualization_msgs::Marker::ADD;
  sheet.pose = pose;
  sheet.scale.x = sheet.scale.y = side;
  sheet.scale.z = kMarkerThickness;
  sheet.color = color;
  return sheet;
}

}  // namespace

geometry_msgs::Pose ToPose(const cv::Vec3d& rvec, const cv::Vec3d& tvec) {
  cv::Matx33d r;
  cv::Rodrigues(rvec, r);
  const tf2::Matrix3x3 rotation(r(0, 0), r(0, 1), r(0, 2), r(1, 0), r(1, 1), r(1, 2), r(2, 0), r(2, 1), r(2, 2));
  tf2::Quaternion q;
  rotation.getRotation(q);
  q.normalize();
  geometry_msgs::Pose pose;
  pose.position.x = tvec[0];
  pose.position.y = tvec[1];
  pose.position.z = tvec[2];
  pose.orientation = tf2::toMsg(q);
  return pose;
}

ArucoTagMsg ToMessage(const ArucoTag& tag) {
  ArucoTagMsg msg;
  msg.id = tag.id;
  for (size_t i = 0; i < tag.corners.size(); ++i) msg.corners[i] = ToPoint(tag.corners[i]);
  msg.center = ToPoint(FindTagCenter(tag));
  msg.pattern_fitted = tag.pattern_fitted;
  msg.side_length = tag.side_length;
  msg.pose_source = static_cast<uint8_t>(tag.pose_source);
  if (tag.HasPose()) {
    msg.pose = ToPose(tag.rvec, tag.tvec);
  } else {
    msg.pose.orientation.w = 1.0;  // a valid quaternion even when there is nothing to say
  }
  for (int i = 0; i < 36; ++i) msg.covariance[i] = tag.covariance.val[i];  // both row-major
  msg.orientation_measured = tag.orientation_measured;
  msg.distance = tag.distance;
  msg.yaw = tag.yaw;
  msg.reprojection_error = tag.reprojection_error;
  msg.ambiguity = tag.pnp.valid ? tag.pnp.ambiguity : kNan;
  msg.depth_disagreement = tag.depth_disagreement;
  msg.cloud_points = tag.cloud.valid ? tag.cloud.points : 0;
  return msg;
}

ArucoTagArray ToMessage(const std::vector<ArucoTag>& tags, const std_msgs::Header& header,
                        const geometry_msgs::TransformStamped* to_output) {
  ArucoTagArray array;
  array.header = header;
  array.camera_frame_id = header.frame_id;
  if (to_output) array.header.frame_id = to_output->header.frame_id;
  array.tags.reserve(tags.size());
  for (const auto& tag : tags) {
    array.tags.push_back(ToMessage(tag));
    if (to_output && tag.HasPose()) {
      tf2::doTransform(array.tags.back().pose, array.tags.back().pose, *to_output);
      RotateCovariance(to_output->transform.rotation, array.tags.back().covariance);
    }
  }
  return array;
}

CameraModel CameraModelFromInfo(const sensor_msgs::CameraInfo& info, bool use_projection, const cv::Size& image_size) {
  image_geometry::PinholeCameraModel geometry;
  try {
    geometry.fromCameraInfo(info);
  } catch (const std::exception& e) {  // image_geometry::Exception
    throw Error(std::string("camera_info not usable: ") + e.what());
  }
  return CameraModelFromInfo(geometry, use_projection, image_size);
}

CameraModel CameraModelFromInfo(const image_geometry::PinholeCameraModel& geometry, bool use_projection,
                                const cv::Size& image_size) {
  namespace models = sensor_msgs::distortion_models;
  if (!geometry.initialized()) throw Error("no camera_info received yet");
  const sensor_msgs::CameraInfo& info = geometry.cameraInfo();
  // image_geometry hands sizes, binning and ROI over as int: a message's uint32 values past this
  // wrap negative or overflow the products below (fuzz_ros: a 2^31 ROI). 32768 px a side is over
  // twice the largest sensors; the checks that follow need sizes to fit an int's area.
  constexpr std::uint32_t kMaxSide = 1u << 15;
  const auto& r = info.roi;
  for (const std::uint32_t value : {info.width, info.height, info.binning_x, info.binning_y, r.x_offset,
                                    r.y_offset, r.width, r.height}) {
    if (value > kMaxSide) {
      throw Error("camera_info size, binning or roi above " + std::to_string(kMaxSide) + " px (" +
                  Size(info.width, info.height) + " sensor, roi " + std::to_string(r.x_offset) + "," +
                  std::to_string(r.y_offset) + " " + Size(r.width, r.height) + ", binning " +
                  Size(info.binning_x, info.binning_y) + ")");
    }
  }
  // image_geometry reads binning 0 as 1 and an all-zero ROI as the whole sensor. K, D and P stay
  // full-resolution; the pixel mapping places this image's pixels on the sensor.
  const int binning_x = static_cast<int>(geometry.binningX()), binning_y = static_cast<int>(geometry.binningY());
  const cv::Rect roi = geometry.rawRoi();
  const cv::Size sensor = geometry.fullResolution();
  const std::string layout = Size(sensor.width, sensor.height) + " sensor, roi " + std::to_string(roi.x) + "," +
                             std::to_string(roi.y) + " " + Size(roi.width, roi.height) + ", binning " +
                             Size(binning_x, binning_y);
  if (sensor.area() > 0 && (roi.area() == 0 || (roi & cv::Rect(cv::Point(), sensor)) != roi)) {
    throw Error("camera_info roi does not lie within the sensor (" + layout + ")");
  }
  if (roi.area() > 0) {
    // What image_geometry's reducedResolution() gives for an unrectified ROI, without the
    // rectification it would run when the ROI asks for do_rectify.
    const cv::Size expected(roi.width / binning_x, roi.height / binning_y);
    if (expected != image_size) {
      throw Error("camera_info is for a " + Size(expected.width, expected.height) + " image (" + layout +
                  ") but the image is " + Size(image_size.width, image_size.height));
    }
  } else if (roi.x != 0 || roi.y != 0) {
    throw Error("camera_info roi has an offset but no size (" + layout + ")");
  }

  const auto all_zero = [](const auto& values) {
    return std::all_of(values.begin(), values.end(), [](double v) { return v == 0.0; });
  };
  const auto all_finite = [](const auto& values) {
    return std::all_of(values.begin(), values.end(), [](double v) { return std::isfinite(v); });
  };
  CameraModel camera;
  const std::string& model = info.distortion_model;
  if (use_projection) {
    if (all_zero(info.P)) throw Error("camera_info P is all zero (uncalibrated camera?)");
    if (!all_finite(info.P)) throw Error("camera_info P has a NaN or infinite entry");
    camera = CameraModel::FromProjection(geometry.fullProjectionMatrix());
  } else {
    if (all_zero(info.K)) throw Error("camera_info K is all zero (uncalibrated camera?)");
    if (!all_finite(info.K)) throw Error("camera_info K has a NaN or infinite entry");
    const cv::Matx33d& K = geometry.fullIntrinsicMatrix();
    if (model == models::EQUIDISTANT) {
      camera = CameraModel::FromFisheye(K, info.D);
    } else if (model == models::PLUMB_BOB || model == models::RATIONAL_POLYNOMIAL || model.empty() ||
               all_zero(info.D)) {
      // Older drivers leave the model empty; OpenCV's pinhole model then reads D by its count.
      camera = CameraModel::FromIntrinsics(K, info.D);
    } else {
      throw Error("camera_info distortion model '" + model + "' is not supported (" + models::PLUMB_BOB + ", " +
                  models::RATIONAL_POLYNOMIAL + ", " + models::EQUIDISTANT +
                  "); rectify the image and set ~rectified");
    }
  }
  camera.pixels = PixelMapping::FromBinningAndRoi(binning_x, binning_y, roi.tl());
  try {
    camera.Validate();
  } catch (const Error& e) {
    throw Error(std::string("camera_info (") + (use_projection ? "P" : model.empty() ? "K" : "K, " + model) +
                "): " + e.what());
  }
  return camera;
}

sensor_msgs::ImagePtr ToImageMessage(const cv::Mat& pixels, const std::string& encoding,
                                     const std_msgs::Header& header) {
  auto image = boost::make_shared<sensor_msgs::Image>();
  image->header = header;
  image->width = static_cast<uint32_t>(pixels.cols);
  image->height = static_cast<uint32_t>(pixels.rows);
  image->encoding = encoding;
  image->is_bigendian = false;
  image->step = static_cast<uint32_t>(pixels.cols * pixels.elemSize());
  image->data.resize(static_cast<size_t>(image->step) * image->height);
  pixels.copyTo(cv::Mat(pixels.rows, pixels.cols, pixels.type(), image->data.data(), image->step));
  return image;
}

pcl::PointCloud<pcl::PointXYZ> CloudFromMessage(const sensor_msgs::PointCloud2& cloud, const cv::Size& image_size,
                                                const geometry_msgs::Transform* transform) {
  pcl::PointCloud<pcl::PointXYZ> points;
  CloudFromMessage(cloud, image_size, transform, points);
  return points;
}

void CloudFromMessage(const sensor_msgs::PointCloud2& cloud, const cv::Size& image_size,
                      const geometry_msgs::Transform* transform, pcl::PointCloud<pcl::PointXYZ>& out) {
  // pcl::fromROSMsg trusts the message: a missing or float64 field leaves zeros (with a warning on
  // the console), a short buffer is read past its end. So everything it relies on is checked here.
  if (cloud.height <= 1 || cloud.width == 0) {
    throw Error("point cloud is not organized (" + Size(cloud.width, cloud.height) +
                "); an organized cloud has one point per image pixel");
  }
  if (cloud.is_bigendian) throw Error("big-endian point clouds are not supported");
  const char* names[3] = {"x", "y", "z"};
  for (int axis = 0; axis < 3; ++axis) {
    const auto field = std::find_if(cloud.fields.begin(), cloud.fields.end(),
                                    [&](const sensor_msgs::PointField& f) { return f.name == names[axis]; });
    if (field == cloud.fields.end()) throw Error(std::string("point cloud has no '") + names[axis] + "' field");
    if (field->datatype != sensor_msgs::PointField::FLOAT32 || field->count != 1) {
      throw Error(std::string("point cloud field '") + names[axis] + "' is not a single float32");
    }
    if (static_cast<size_t>(field->offset) + sizeof(float) > cloud.point_step) {
      throw Error(std::string("point cloud field '") + names[axis] + "' lies beyond point_step");
    }
  }
  if (cloud.row_step < static_cast<size_t>(cloud.width) * cloud.point_step ||
      cloud.data.size() < static_cast<size_t>(cloud.row_step) * cloud.height) {
    throw Error("point cloud buffer is shorter than " + Size(cloud.width, cloud.height) + " points of " +
                std::to_string(cloud.point_step) + " bytes");
  }
  const int factor = image_size.width / static_cast<int>(cloud.width);
  if (cv::Size(cloud.width, cloud.height) != image_size &&
      (factor < 2 || static_cast<int>(cloud.width) * factor != image_size.width ||
       static_cast<int>(cloud.height) * factor != image_size.height)) {
    throw Error("point cloud is " + Size(cloud.width, cloud.height) + " but the image is " +
                Size(image_size.width, image_size.height) +
                "; an organized cloud must match the image pixel for pixel or be it downscaled by a whole factor");
  }

  // A cloud the image's size is read straight into `out` (its buffer reused); a smaller one first
  // into `small`, then enlarged into `out`.
  thread_local pcl::PointCloud<pcl::PointXYZ> small;
  pcl::PointCloud<pcl::PointXYZ>& points = factor < 2 ? out : small;
  pcl::fromROSMsg(cloud, points);
  if (transform) {
    // Non-finite points are left as they are: holes stay holes.
    const Eigen::Affine3f to_image =
        Eigen::Translation3f(static_cast<float>(transform->translation.x), static_cast<float>(transform->translation.y),
                             static_cast<float>(transform->translation.z)) *
        Eigen::Quaternionf(static_cast<float>(transform->rotation.w), static_cast<float>(transform->rotation.x),
                           static_cast<float>(transform->rotation.y), static_cast<float>(transform->rotation.z))
            .normalized();
    pcl::transformPointCloud(points, points, to_image);
  }
  if (factor < 2) return;
  // A depth camera's cloud at a fraction of the image resolution: each point covers a block. A
  // PointXYZ is x, y, z and a padding float, so OpenCV resizes the points as a 4-channel image.
  static_assert(sizeof(pcl::PointXYZ) == 4 * sizeof(float), "pcl::PointXYZ is x, y, z and one padding float");
  // points.resize, width, height by hand: PCL 1.10 (Noetic) has no resize(width, height).
  out.points.resize(static_cast<size_t>(image_size.area()));
  out.width = static_cast<uint32_t>(image_size.width);
  out.height = static_cast<uint32_t>(image_size.height);
  out.header = points.header;
  out.is_dense = points.is_dense;
  const cv::Mat from(static_cast<int>(points.height), static_cast<int>(points.width), CV_32FC4, points.points.data());
  cv::Mat to(image_size, CV_32FC4, out.points.data());
  cv::resize(from, to, image_size, 0.0, 0.0, cv::INTER_NEAREST);
}

visualization_msgs::MarkerArray ClearedMarkers(const std_msgs::Header& header) {
  visualization_msgs::MarkerArray markers;
  visualization_msgs::Marker clear;
  clear.header = header;
  clear.action = visualization_msgs::Marker::DELETEALL;
  markers.markers.push_back(clear);
  return markers;
}

visualization_msgs::MarkerArray ToMarkers(const ArucoTagArray& tags) {
  visualization_msgs::MarkerArray markers = ClearedMarkers(tags.header);
  int next_id = 0;
  for (const auto& tag : tags.tags) {
    if (tag.pose_source == ArucoTagMsg::NONE) continue;
    const visualization_msgs::Marker box =
        Sheet(tags.header, "aruco_tags", next_id++, tag.pose, tag.side_length, Rgba(0.0f, 0.8f, 0.2f, 0.8f));
    markers.markers.push_back(box);

    visualization_msgs::Marker label = box;
    label.ns = "aruco_labels";
    label.type = visualization_msgs::Marker::TEXT_VIEW_FACING;
    label.text = std::to_string(tag.id);
    // Above the tag along its own y (the printed "up"), so the label never hides the box.
    tf2::Quaternion q;
    tf2::fromMsg(tag.pose.orientation, q);
    const tf2::Vector3 up = tf2::quatRotate(q, tf2::Vector3(0.0, 0.75 * tag.side_length, 0.0));
    label.pose.position.x += up.x();
    label.pose.position.y += up.y();
    label.pose.position.z += up.z();
    label.scale.x = label.scale.y = 0.0;
    label.scale.z = std::max(0.05, 0.4 * tag.side_length);
    label.color.r = label.color.g = label.color.b = label.color.a = 1.0f;
    markers.markers.push_back(label);
  }
  return markers;
}

visualization_msgs::MarkerArray ToBundleMarkers(const BundleArray& array, const std::vector<MarkerBundle>& bundles) {
  visualization_msgs::MarkerArray markers = ClearedMarkers(array.header);
  int next_id = 0;
  for (const auto& seen : array.bundles) {
    const auto config = std::find_if(bundles.begin(), bundles.end(),
                                     [&seen](const MarkerBundle& b) { return b.name == seen.name; });
    if (config == bundles.end()) continue;
    tf2::Transform bundle;
    tf2::fromMsg(seen.pose.pose, bundle);
    double top = 0.0;  // m, the highest face centre above the origin along the bundle's z
    for (const auto& member : config->members) {
      const cv::Matx33d& r = member.rotation;
      const tf2::Transform in_bundle(
          tf2::Matrix3x3(r(0, 0), r(0, 1), r(0, 2), r(1, 0), r(1, 1), r(1, 2), r(2, 0), r(2, 1), r(2, 2)),
          tf2::Vector3(member.position[0], member.position[1], member.position[2]));
      geometry_msgs::Pose pose;
      tf2::toMsg(bundle * in_bundle, pose);
      markers.markers.push_back(
          Sheet(array.header, "aruco_bundles", next_id++, pose, member.side_length, Rgba(0.55f, 0.35f, 1.0f, 0.85f)));
      top = std::max(top, member.position[2] + 0.5 * member.side_length);
    }
    visualization_msgs::Marker label;
    label.header = array.header;
    label.ns = "aruco_bundle_labels";
    label.id = next_id++;
    label.type = visualization_msgs::Marker::TEXT_VIEW_FACING;
    label.action = visualization_msgs::Marker::ADD;
    tf2::toMsg(bundle * tf2::Transform(tf2::Quaternion::getIdentity(), tf2::Vector3(0.0, 0.0, top + 0.1)), label.pose);
    label.pose.orientation = geometry_msgs::Quaternion();
    label.pose.orientation.w = 1.0;
    label.scale.z = 0.1;
    label.color.r = label.color.g = label.color.b = label.color.a = 1.0f;
    label.text = seen.name;
    markers.markers.push_back(label);
  }
  return markers;
}

geometry_msgs::TransformStamped ToTransform(const ArucoTagMsg& tag, const std_msgs::Header& header,
                                            const std::string& child_frame) {
  return ToTransform(tag.pose, header, child_frame);
}

geometry_msgs::TransformStamped ToTransform(const geometry_msgs::Pose& pose, const std_msgs::Header& header,
                                            const std::string& child_frame) {
  geometry_msgs::TransformStamped transform;
  transform.header = header;
  transform.child_frame_id = child_frame;
  transform.transform.translation.x = pose.position.x;
  transform.transform.translation.y = pose.position.y;
  transform.transform.translation.z = pose.position.z;
  transform.transform.rotation = pose.orientation;
  return transform;
}

BundleArray ToMessage(const std::vector<BundlePose>& bundles, const std::vector<std::string>& child_frames,
                      const std_msgs::Header& header, const geometry_msgs::TransformStamped* to_output) {
  BundleArray array;
  array.header = header;
  array.camera_frame_id = header.frame_id;
  if (to_output) array.header.frame_id = to_output->header.frame_id;
  for (size_t i = 0; i < bundles.size(); ++i) {
    const BundlePose& b = bundles[i];
    if (!b.valid) continue;
    Bundle msg;
    msg.name = b.name;
    msg.child_frame_id = i < child_frames.size() ? child_frames[i] : std::string();
    msg.pose_source = b.pose_source == PoseSource::kFused ? Bundle::FUSED : Bundle::PNP;
    msg.camera_pose.pose = ToPose(b.rvec, b.tvec);
    std::copy(b.covariance.val, b.covariance.val + 36, msg.camera_pose.covariance.begin());  // both row-major
    msg.pose = msg.camera_pose;
    if (to_output) {
      tf2::doTransform(msg.camera_pose.pose, msg.pose.pose, *to_output);
      RotateCovariance(to_output->transform.rotation, msg.pose.covariance);
    }
    msg.member_ids = b.member_ids;
    msg.reprojection_error = b.reprojection_error;
    array.bundles.push_back(msg);
  }
  return array;
}

bool BetterMeasured(const ArucoTagMsg& a, const ArucoTagMsg& b) {
  const bool a_pose = a.pose_source != ArucoTagMsg::NONE, b_pose = b.pose_source != ArucoTagMsg::NONE;
  if (a_pose != b_pose) return a_pose;
  if (std::isfinite(a.reprojection_error) && std::isfinite(b.reprojection_error)) {
    return a.reprojection_error < b.reprojection_error;
  }
  if (std::isfinite(a.reprojection_error) != std::isfinite(b.reprojection_error)) {
    return std::isfinite(a.reprojection_error);
  }
  return a.cloud_points > b.cloud_points;
}

}  // namespace arucotag

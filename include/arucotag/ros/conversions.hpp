#pragma once

// The one place where core types meet ROS messages. Nothing here logs; errors are arucotag::Error.
#include <arucotag/ros/messages.hpp>

#include <string>
#include <vector>

#include <geometry_msgs/Pose.h>
#include <geometry_msgs/Transform.h>
#include <geometry_msgs/TransformStamped.h>
#include <image_geometry/pinhole_camera_model.h>
#include <opencv2/core.hpp>
#include <pcl/point_cloud.h>
#include <pcl/point_types.h>
#include <sensor_msgs/CameraInfo.h>
#include <sensor_msgs/Image.h>
#include <sensor_msgs/PointCloud2.h>
#include <std_msgs/Header.h>
#include <visualization_msgs/MarkerArray.h>

#include <arucotag/BundleArray.h>
#include <arucotag/aruco_tag.hpp>
#include <arucotag/bundle.hpp>
#include <arucotag/pose.hpp>

namespace arucotag {

/// Marker -> camera rotation (Rodrigues) and marker centre (m) as a geometry_msgs/Pose.
geometry_msgs::Pose ToPose(const cv::Vec3d& rvec, const cv::Vec3d& tvec);

/// One detection as a message, pose in the camera optical frame. Fields without a measurement
/// (no pose, no PnP, no cloud) are NaN or 0 as msg/ArucoTag.msg documents.
ArucoTagMsg ToMessage(const ArucoTag& tag);

/// All detections of one frame. `header` is the image's; when `to_output` is given the poses are
/// moved by it and the header's frame_id becomes its parent frame (the ~output_frame).
/// camera_frame_id is the image's frame_id either way.
ArucoTagArray ToMessage(const std::vector<ArucoTag>& tags, const std_msgs::Header& header,
                        const geometry_msgs::TransformStamped* to_output = nullptr);

/// The camera model of an image from its camera_info, read through image_geometry. use_projection:
/// P's left 3x3 block and no distortion (for rectified images); otherwise K and D, plumb_bob,
/// rational_polynomial or equidistant (fisheye). K, D and P stay the full-resolution calibration;
/// binning and ROI become the model's pixel mapping (see PixelMapping::FromBinningAndRoi), so
/// poses from a binned or cropped image are full-resolution poses. Throws arucotag::Error when the
/// matrix used is all zero (an uncalibrated driver) or has a NaN/infinite entry, fx/fy are not
/// positive, the distortion model is unknown (with non-zero D; an empty name reads D as OpenCV's
/// pinhole model) or has the wrong coefficient count, the ROI lies outside the sensor, or
/// `image_size` differs from the ROI's size divided by the binning (not checked when the info
/// states no size).
CameraModel CameraModelFromInfo(const sensor_msgs::CameraInfo& info, bool use_projection, const cv::Size& image_size);
/// The same from an image_geometry model a nodelet keeps updated with fromCameraInfo().
CameraModel CameraModelFromInfo(const image_geometry::PinholeCameraModel& geometry, bool use_projection,
                                const cv::Size& image_size);

/// An 8- or 16-bit image as a message with the given encoding and header (the pixels are copied).
sensor_msgs::ImagePtr ToImageMessage(const cv::Mat& pixels, const std::string& encoding,
                                     const std_msgs::Header& header);

/// An organized PointCloud2 (float32 x, y, z fields at any offsets and point_step, little-endian)
/// as a pcl::PointCloud<pcl::PointXYZ> of image_size (pcl::fromROSMsg), each point moved by
/// `transform` when given (NaN points stay NaN). A cloud smaller than the image by a whole factor
/// (a depth camera at a fraction of the image's resolution) is enlarged to it, each point covering
/// its block. Throws on an unorganized cloud, missing or non-float32 x/y/z fields, fields beyond
/// point_step, big-endian data, a buffer shorter than its declared size, or another size.
pcl::PointCloud<pcl::PointXYZ> CloudFromMessage(const sensor_msgs::PointCloud2& cloud, const cv::Size& image_size,
                                                const geometry_msgs::Transform* transform = nullptr);
/// The same into `out`, whose point buffer is reused (a nodelet converting a 1280x720 cloud every
/// frame keeps one 15 MB buffer instead of allocating and freeing one per frame). On a throw `out`
/// is unspecified.
void CloudFromMessage(const sensor_msgs::PointCloud2& cloud, const cv::Size& image_size,
                      const geometry_msgs::Transform* transform, pcl::PointCloud<pcl::PointXYZ>& out);

/// The opener of every MarkerArray published here: one DELETEALL with `header`, so markers of
/// tags, tracks or bundles that disappeared since the last array are cleared.
visualization_msgs::MarkerArray ClearedMarkers(const std_msgs::Header& header);

/// The rviz view of a tag array: a DELETEALL first (so tags that disappear are cleared), then per
/// tag with a pose a flat CUBE (side x side x 5 mm) at its pose and a TEXT_VIEW_FACING id label
/// just above it. Stamp and frame are the array's.
visualization_msgs::MarkerArray ToMarkers(const ArucoTagArray& tags);

/// The rviz view of the bundles of one frame: a DELETEALL first, then per bundle in view every member
/// of its configuration in `bundles` (found by name) as a flat CUBE at the bundle pose times the
/// member's pose (faces in view and out of view alike: the whole object where it stands), and a
/// TEXT_VIEW_FACING label with the bundle's name above the bundle origin. Stamp and frame are the array's.
visualization_msgs::MarkerArray ToBundleMarkers(const BundleArray& array, const std::vector<MarkerBundle>& bundles);

/// The TF of one tag: parent = header.frame_id, child = `child_frame`, stamp = header.stamp.
geometry_msgs::TransformStamped ToTransform(const ArucoTagMsg& tag, const std_msgs::Header& header,
                                            const std::string& child_frame);
/// The same for any pose in header.frame_id.
geometry_msgs::TransformStamped ToTransform(const geometry_msgs::Pose& pose, const std_msgs::Header& header,
                                            const std::string& child_frame);

/// The bundles of one frame (those with a valid pose). `header` is the image's: camera_pose stays
/// in its frame; pose is moved by `to_output` when given, and the header's frame_id becomes its
/// parent frame (the ~output_frame). `child_frames[i]` names bundles[i]'s TF child frame.
BundleArray ToMessage(const std::vector<BundlePose>& bundles, const std::vector<std::string>& child_frames,
                      const std_msgs::Header& header, const geometry_msgs::TransformStamped* to_output = nullptr);

/// Whether `a` is better measured than `b` (for choosing which of several faces with one id gets
/// the TF): a pose beats none; with PnP on both, the lower reprojection error; otherwise more
/// cloud points.
bool BetterMeasured(const ArucoTagMsg& a, const ArucoTagMsg& b);

}  // namespace arucotag

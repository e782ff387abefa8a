#pragma once

// Real photos for the rostests: UbiquityRobotics/fiducials' Raspberry Pi camera shots (1280x960,
// DICT_5X5_1000, 0.145 m markers), with the corners their own suite asserts and the calibration
// they ship, published as the camera would.
#include <array>
#include <map>
#include <string>
#include <vector>

#include <opencv2/core.hpp>
#include <ros/time.h>
#include <sensor_msgs/CameraInfo.h>
#include <sensor_msgs/Image.h>

namespace arucotag::test {

using Quad = std::array<cv::Point2d, 4>;

constexpr double kPhotoSide = 0.145;  ///< m, the photos' marker side
constexpr const char* kPhotoFrame = "raspicam_optical";
/// The calibration UbiquityRobotics/fiducials ships with these photos (plumb_bob).
inline const cv::Matx33d kPhotoK(1006.126285753055, 0, 655.8639244150409, 0, 1004.015433012594, 490.6140221242933, 0,
                                 0, 1);
inline const std::vector<double> kPhotoD{0.1349735087283542, -0.2335869827451621, 0.0006697030315075139,
                                         0.004846737465872353, 0.0};

struct Photo {
  cv::Mat bgr;
  std::map<int, Quad> corners;  ///< the upstream suite's corners (OpenCV sub-pixel)
};

/// Markers 245 and 246, 0.6-0.7 m away.
const Photo& TwoTags();
/// Marker 1.
const Photo& OneTag();

/// The pose the reference corners give under a calibration (marker -> optical frame).
void ReferencePose(const Quad& corners, cv::Matx33d& rotation, cv::Vec3d& position, const cv::Matx33d& k = kPhotoK,
                   const std::vector<double>& d = kPhotoD);

/// The camera's camera_info (1280x960, plumb_bob K, D; P = K).
sensor_msgs::CameraInfoPtr RaspiInfo(const ros::Time& stamp, const std::string& frame = kPhotoFrame,
                                     const cv::Matx33d& k = kPhotoK, const std::vector<double>& d = kPhotoD);

/// The photo as a bgr8 image.
sensor_msgs::ImagePtr PhotoImage(const Photo& photo, const ros::Time& stamp, const std::string& frame = kPhotoFrame);

}  // namespace arucotag::test

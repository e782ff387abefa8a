#pragma once

// The tracker (include/arucotag/tracker.hpp) meets ROS here: its tracks as messages and rviz markers,
// TF transforms as the rigid motions it takes. Nothing here logs; errors are arucotag::Error.
#include <vector>

#include <arucotag/TagTracks.h>
#include <geometry_msgs/Transform.h>
#include <opencv2/core.hpp>
#include <std_msgs/Header.h>
#include <visualization_msgs/MarkerArray.h>

#include <arucotag/tracker.hpp>

namespace arucotag {

/// A transform as rotation and translation (points of the child frame into the parent frame).
void ToRigid(const geometry_msgs::Transform& transform, cv::Matx33d& rotation, cv::Vec3d& translation);

/// Every track as a message: `header` is the image's with the frame of the poses; `filtered` says
/// whether the poses are Kalman-filtered (TrackerConfig::filter) or the last detection's.
TagTracks ToMessage(const std::vector<Track>& tracks, const std_msgs::Header& header, bool filtered);

/// The rviz view of the tracks: a DELETEALL first, then per track its position's 3-sigma covariance
/// ellipsoid (a SPHERE scaled along the covariance's axes, at least 1 cm across; green when validated,
/// orange before) and a TEXT_VIEW_FACING label "id (hits)" above it. Stamp and frame are the array's.
visualization_msgs::MarkerArray ToTrackMarkers(const TagTracks& tracks);

}  // namespace arucotag

#pragma once

// The tracker (include/arucotag/tracker.hpp) meets ROS here: its tracks as messages and rviz markers,
// TF transforms as the rigid motions it takes, tag arrays as its measurements. Nothing here logs;
// errors are arucotag::Error.
#include <arucotag/ros/messages.hpp>  // first: it renames the generated ArucoTag message

#include <cstdint>
#include <map>
#include <vector>

#include <arucotag/TagTracks.h>
#include <geometry_msgs/Pose.h>
#include <geometry_msgs/Transform.h>
#include <ros/time.h>
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

/// The same for a tracker right after its Update with the frame stamped `frame_stamp` (`filtered`:
/// its config's `filter`; `header` is usually that frame's, with the tracks' frame). The core keeps
/// stamps as double seconds, a fraction of a microsecond off today's stamps: each track's last_seen
/// is the exact stamp of the frame of its last hit instead, from `last_seen` (per track id; the
/// caller keeps it from one frame to the next, this updates it).
TagTracks ToMessage(const TagTracker& tracker, const std_msgs::Header& header, const ros::Time& frame_stamp,
                    std::map<std::uint32_t, ros::Time>& last_seen);

/// The detections of a tag array as tracker measurements in the array's frame (header.frame_id):
/// every tag with a pose and a finite covariance, as MeasurementsInFrame gives them. The message
/// carries the chosen planar solution only, so none has an alternative.
std::vector<TrackMeasurement> MeasurementsFromMessage(const ArucoTagArray& tags);

/// Per marker id, the pose of its most-seen validated track: what TF publishes from tracks.
std::map<int, geometry_msgs::Pose> ValidatedPoses(const TagTracks& tracks);

/// The rviz view of the tracks: a DELETEALL first, then per track its position's 3-sigma covariance
/// ellipsoid (a SPHERE scaled along the covariance's axes, at least 1 cm across; green when validated,
/// orange before) and a TEXT_VIEW_FACING label "id (hits)" above it. Stamp and frame are the array's.
visualization_msgs::MarkerArray ToTrackMarkers(const TagTracks& tracks);

}  // namespace arucotag

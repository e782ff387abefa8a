#include <arucotag/ros/conversions.hpp>  // first: it renames the generated ArucoTag message
#include <arucotag/ros/tracks.hpp>

#include <algorithm>
#include <cmath>

#include <tf2/LinearMath/Matrix3x3.h>
#include <tf2/LinearMath/Quaternion.h>
#include <tf2_geometry_msgs/tf2_geometry_msgs.h>

namespace arucotag {

namespace {

constexpr double kSigmas = 3.0;          // the ellipsoid's half-axes, in standard deviations
constexpr double kSmallestAxis = 0.01;   // m: a well-measured track stays visible

geometry_msgs::Quaternion ToQuaternion(const cv::Matx33d& r) {
  tf2::Quaternion q;
  tf2::Matrix3x3(r(0, 0), r(0, 1), r(0, 2), r(1, 0), r(1, 1), r(1, 2), r(2, 0), r(2, 1), r(2, 2)).getRotation(q);
  q.normalize();
  return tf2::toMsg(q);
}

}  // namespace

void ToRigid(const geometry_msgs::Transform& transform, cv::Matx33d& rotation, cv::Vec3d& translation) {
  tf2::Quaternion q;
  tf2::fromMsg(transform.rotation, q);
  const tf2::Matrix3x3 m(q);
  for (int i = 0; i < 3; ++i) {
    for (int j = 0; j < 3; ++j) rotation(i, j) = m[i][j];
  }
  translation = {transform.translation.x, transform.translation.y, transform.translation.z};
}

TagTracks ToMessage(const std::vector<Track>& tracks, const std_msgs::Header& header, bool filtered) {
  TagTracks msg;
  msg.header = header;
  msg.tracks.reserve(tracks.size());
  for (const auto& track : tracks) {
    TagTrack t;
    t.track_id = track.track_id;
    t.id = track.id;
    t.cameras = track.cameras;
    t.validated = track.validated;
    t.hits = static_cast<uint32_t>(track.hits);
    t.misses = static_cast<uint32_t>(track.misses);
    t.outliers = static_cast<uint32_t>(track.outliers);
    t.age = track.age;
    t.last_seen = ros::Time(std::max(0.0, track.last_seen));
    t.filtered = filtered;
    t.pose.pose.position.x = track.position[0];
    t.pose.pose.position.y = track.position[1];
    t.pose.pose.position.z = track.position[2];
    t.pose.pose.orientation = ToQuaternion(track.rotation);
    std::copy(track.covariance.val, track.covariance.val + 36, t.pose.covariance.begin());
    msg.tracks.push_back(std::move(t));
  }
  return msg;
}

TagTracks ToMessage(const TagTracker& tracker, const std_msgs::Header& header, const ros::Time& frame_stamp,
                    std::map<std::uint32_t, ros::Time>& last_seen) {
  TagTracks msg = ToMessage(tracker.Tracks(), header, tracker.Config().filter);
  std::map<std::uint32_t, ros::Time> kept;
  for (size_t i = 0; i < msg.tracks.size(); ++i) {
    TagTrack& track = msg.tracks[i];
    const auto known = last_seen.find(track.track_id);
    const bool hit_now = tracker.Tracks()[i].last_seen == frame_stamp.toSec() || known == last_seen.end();
    track.last_seen = kept[track.track_id] = hit_now ? frame_stamp : known->second;
  }
  last_seen.swap(kept);
  return msg;
}

std::vector<TrackMeasurement> MeasurementsFromMessage(const ArucoTagArray& tags) {
  std::vector<TrackMeasurement> measurements;
  for (const auto& tag : tags.tags) {
    const bool finite = std::all_of(tag.covariance.begin(), tag.covariance.end(), [](double v) { return std::isfinite(v); });
    if (tag.pose_source == ArucoTagMsg::NONE || !finite) continue;
    TrackMeasurement m;
    m.id = tag.id;
    m.position = {tag.pose.position.x, tag.pose.position.y, tag.pose.position.z};
    tf2::Quaternion q;
    tf2::fromMsg(tag.pose.orientation, q);
    const tf2::Matrix3x3 r(q.normalized());
    for (int i = 0; i < 3; ++i) {
      for (int j = 0; j < 3; ++j) m.rotation(i, j) = r[i][j];
    }
    std::copy(tag.covariance.begin(), tag.covariance.end(), m.covariance.val);  // both row-major
    measurements.push_back(m);
  }
  return measurements;
}

std::map<int, geometry_msgs::Pose> ValidatedPoses(const TagTracks& tracks) {
  std::map<int, geometry_msgs::Pose> poses;
  std::map<int, uint32_t> hits;
  for (const auto& track : tracks.tracks) {
    if (!track.validated || track.hits <= hits[track.id]) continue;
    hits[track.id] = track.hits;
    poses[track.id] = track.pose.pose;
  }
  return poses;
}

visualization_msgs::MarkerArray ToTrackMarkers(const TagTracks& tracks) {
  visualization_msgs::MarkerArray markers = ClearedMarkers(tracks.header);
  for (const auto& track : tracks.tracks) {
    const auto& c = track.pose.covariance;
    const cv::Matx33d position(c[0], c[1], c[2], c[6], c[7], c[8], c[12], c[13], c[14]);
    cv::Matx31d values;
    cv::Matx33d vectors;  // rows: unit axes, largest first
    const bool finite = std::all_of(position.val, position.val + 9, [](double v) { return std::isfinite(v); });
    if (!finite || !cv::eigen(position, values, vectors)) {
      values = cv::Matx31d::zeros();
      vectors = cv::Matx33d::eye();
    }
    cv::Matx33d axes = vectors.t();  // columns: the ellipsoid's axes in the frame
    if (cv::determinant(axes) < 0.0) {
      for (int i = 0; i < 3; ++i) axes(i, 2) = -axes(i, 2);
    }
    visualization_msgs::Marker ellipsoid;
    ellipsoid.header = tracks.header;
    ellipsoid.ns = "aruco_tracks";
    ellipsoid.id = static_cast<int>(track.track_id);
    ellipsoid.type = visualization_msgs::Marker::SPHERE;
    ellipsoid.action = visualization_msgs::Marker::ADD;
    ellipsoid.pose.position = track.pose.pose.position;
    ellipsoid.pose.orientation = ToQuaternion(axes);
    ellipsoid.scale.x = std::max(kSmallestAxis, 2.0 * kSigmas * std::sqrt(std::max(0.0, values(0))));
    ellipsoid.scale.y = std::max(kSmallestAxis, 2.0 * kSigmas * std::sqrt(std::max(0.0, values(1))));
    ellipsoid.scale.z = std::max(kSmallestAxis, 2.0 * kSigmas * std::sqrt(std::max(0.0, values(2))));
    ellipsoid.color.r = track.validated ? 0.1f : 1.0f;
    ellipsoid.color.g = track.validated ? 0.9f : 0.55f;
    ellipsoid.color.b = 0.1f;
    ellipsoid.color.a = 0.6f;
    markers.markers.push_back(ellipsoid);

    visualization_msgs::Marker label = ellipsoid;
    label.ns = "aruco_track_labels";
    label.type = visualization_msgs::Marker::TEXT_VIEW_FACING;
    label.pose.orientation = geometry_msgs::Quaternion();
    label.pose.orientation.w = 1.0;
    label.pose.position.z += 0.5 * ellipsoid.scale.z + 0.1;
    label.scale.x = label.scale.y = 0.0;
    label.scale.z = 0.1;
    label.color.a = 1.0f;
    label.text = std::to_string(track.id) + " (" + std::to_string(track.hits) + ")";
    markers.markers.push_back(label);
  }
  return markers;
}

}  // namespace arucotag

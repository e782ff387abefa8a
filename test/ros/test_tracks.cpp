// The tracks' ROS side without a master: MeasurementInFrame agrees with the tags' own move into
// ~output_frame, the message carries the track, and the rviz ellipsoid is the covariance's.
#include <cmath>

#include <gtest/gtest.h>
#include <opencv2/calib3d.hpp>
#include <tf2/LinearMath/Matrix3x3.h>
#include <tf2/LinearMath/Quaternion.h>
#include <tf2_geometry_msgs/tf2_geometry_msgs.h>

#include <arucotag/ros/conversions.hpp>
#include <arucotag/ros/tracks.hpp>

namespace arucotag {
namespace {

// Id 5 with a PnP pose 3 m ahead and a covariance with a range-rotation correlation.
ArucoTag PnpTag() {
  ArucoTag tag;
  tag.id = 5;
  tag.pose_source = PoseSource::kPnp;
  tag.rvec = cv::Vec3d(0.3, -0.2, 0.1);
  tag.tvec = cv::Vec3d(0.4, -0.3, 3.0);
  tag.covariance = PoseCovariance::zeros();
  const double diagonal[6] = {1e-6, 4e-6, 9e-4, 1e-4, 4e-4, 1e-5};
  for (int i = 0; i < 6; ++i) tag.covariance(i, i) = diagonal[i];
  tag.covariance(2, 4) = tag.covariance(4, 2) = 7e-6;
  return tag;
}

TEST(Tracks, MeasurementInFrameMatchesTheTagMessageInOutputFrame) {
  const ArucoTag tag = PnpTag();

  geometry_msgs::TransformStamped to_odom;
  to_odom.header.frame_id = "odom";
  tf2::Quaternion q;
  q.setRPY(0.2, -0.4, 1.1);
  to_odom.transform.rotation = tf2::toMsg(q);
  to_odom.transform.translation.x = 3.0;
  to_odom.transform.translation.y = -1.0;
  to_odom.transform.translation.z = 0.5;
  std_msgs::Header header;
  header.frame_id = "cam";
  const ArucoTagArray array = ToMessage({tag}, header, &to_odom);

  cv::Matx33d rotation;
  cv::Vec3d translation;
  ToRigid(to_odom.transform, rotation, translation);
  const TrackMeasurement m = MeasurementInFrame(tag, rotation, translation);
  const auto& pose = array.tags[0].pose;
  EXPECT_NEAR(m.position[0], pose.position.x, 1e-12);
  EXPECT_NEAR(m.position[1], pose.position.y, 1e-12);
  EXPECT_NEAR(m.position[2], pose.position.z, 1e-12);
  tf2::Quaternion orientation;
  tf2::fromMsg(pose.orientation, orientation);
  const tf2::Matrix3x3 r(orientation);
  for (int i = 0; i < 3; ++i) {
    for (int j = 0; j < 3; ++j) EXPECT_NEAR(m.rotation(i, j), r[i][j], 1e-9);
  }
  for (int i = 0; i < 36; ++i) EXPECT_NEAR(m.covariance.val[i], array.tags[0].covariance[i], 1e-15) << i;
}

// The fuser's measurements, read back from a detector's tags in ~output_frame, are the detector's own
// tracker's (MeasurementsInFrame): same pose, same covariance; a tag without a pose gives none.
TEST(Tracks, MeasurementsFromMessageAreTheDetectorsOwn) {
  const ArucoTag seen = PnpTag();
  ArucoTag corners_only;
  corners_only.id = 9;

  geometry_msgs::TransformStamped to_odom;
  to_odom.header.frame_id = "odom";
  tf2::Quaternion q;
  q.setRPY(-0.3, 0.1, 2.0);
  to_odom.transform.rotation = tf2::toMsg(q);
  to_odom.transform.translation.x = -2.0;
  to_odom.transform.translation.z = 1.5;
  std_msgs::Header header;
  header.frame_id = "front_optical";
  const ArucoTagArray array = ToMessage({corners_only, seen}, header, &to_odom);
  EXPECT_EQ(array.header.frame_id, "odom");
  EXPECT_EQ(array.camera_frame_id, "front_optical");

  cv::Matx33d rotation;
  cv::Vec3d translation;
  ToRigid(to_odom.transform, rotation, translation);
  const std::vector<TrackMeasurement> own = MeasurementsInFrame({corners_only, seen}, rotation, translation);
  const std::vector<TrackMeasurement> read = MeasurementsFromMessage(array);
  ASSERT_EQ(own.size(), 1u);
  ASSERT_EQ(read.size(), 1u);
  EXPECT_EQ(read[0].id, 5);
  for (int i = 0; i < 3; ++i) EXPECT_NEAR(read[0].position[i], own[0].position[i], 1e-12);
  for (int i = 0; i < 9; ++i) EXPECT_NEAR(read[0].rotation.val[i], own[0].rotation.val[i], 1e-9) << i;
  for (int i = 0; i < 36; ++i) EXPECT_NEAR(read[0].covariance.val[i], own[0].covariance.val[i], 1e-15) << i;
  EXPECT_FALSE(read[0].has_alternative);
}

// TF from tracks: per id the most-seen validated track; unvalidated ones never.
TEST(Tracks, ValidatedPosesTakeTheMostSeenValidatedTrackPerId) {
  TagTracks tracks;
  const auto add = [&tracks](int id, bool validated, uint32_t hits, double x) {
    TagTrack t;
    t.id = id;
    t.validated = validated;
    t.hits = hits;
    t.pose.pose.position.x = x;
    t.pose.pose.orientation.w = 1.0;
    tracks.tracks.push_back(t);
  };
  add(1, true, 5, 1.0);
  add(1, true, 9, 2.0);   // the same id on another face, seen more
  add(1, false, 20, 3.0);  // not validated: never TF
  add(2, false, 4, 4.0);
  add(3, true, 3, 5.0);
  const std::map<int, geometry_msgs::Pose> poses = ValidatedPoses(tracks);
  ASSERT_EQ(poses.size(), 2u);
  EXPECT_EQ(poses.at(1).position.x, 2.0);
  EXPECT_EQ(poses.at(3).position.x, 5.0);
}

// The tracks' message after an update keeps each track's exact last-seen stamp, also for a track
// another camera saw last (the fuser: frames of two cameras, header at the latest stamp).
TEST(Tracks, TrackerMessageKeepsExactLastSeenStamps) {
  TagTracker tracker;
  std::map<std::uint32_t, ros::Time> last_seen;
  TrackMeasurement m;
  m.id = 4;
  m.position = cv::Vec3d(5.0, 0.0, 1.0);
  m.covariance = PoseCovariance::eye() * 1e-4;
  std_msgs::Header header;
  header.frame_id = "odom";
  const ros::Time front(1700000000, 123456789), rear(1700000000, 160000001);
  tracker.Update("front", front.toSec(), {m});
  header.stamp = front;
  TagTracks msg = ToMessage(tracker, header, front, last_seen);
  ASSERT_EQ(msg.tracks.size(), 1u);
  EXPECT_EQ(msg.tracks[0].last_seen, front);
  tracker.Update("rear", rear.toSec(), {m});
  header.stamp = rear;
  msg = ToMessage(tracker, header, rear, last_seen);
  EXPECT_EQ(msg.tracks[0].last_seen, rear);
  EXPECT_TRUE(msg.tracks[0].filtered);
  tracker.Update("front", front.toSec() + 1e-3, {});  // a late frame of the other camera, without it
  msg = ToMessage(tracker, header, front + ros::Duration(1e-3), last_seen);
  EXPECT_EQ(msg.tracks[0].last_seen, rear);
}

TEST(Tracks, MessageAndEllipsoidCarryTheTrack) {
  Track track;
  track.track_id = 7;
  track.id = 1;
  track.cameras = {"zed_left_camera_optical_frame"};
  track.validated = true;
  track.hits = 12;
  track.misses = 2;
  track.outliers = 1;
  track.age = 0.8;
  track.last_seen = 100.25;
  track.position = cv::Vec3d(7.6, -1.0, 0.6);
  cv::Rodrigues(cv::Vec3d(0, 0, 0.5), track.rotation);
  // Position sigmas 1, 2 and 3 cm along axes turned 30 degrees about z.
  const double c = std::cos(M_PI / 6), s = std::sin(M_PI / 6);
  const cv::Matx33d axes(c, -s, 0, s, c, 0, 0, 0, 1);
  const cv::Matx33d position = axes * cv::Matx33d::diag({1e-4, 4e-4, 9e-4}) * axes.t();
  track.covariance = PoseCovariance::zeros();
  for (int i = 0; i < 3; ++i) {
    for (int j = 0; j < 3; ++j) track.covariance(i, j) = position(i, j);
    track.covariance(3 + i, 3 + i) = 1e-4;
  }
  std_msgs::Header header;
  header.frame_id = "odom";
  header.stamp = ros::Time(100.3);
  Track young = track;
  young.track_id = 8;
  young.validated = false;
  const TagTracks msg = ToMessage({track, young}, header, true);
  ASSERT_EQ(msg.tracks.size(), 2u);
  const TagTrack& t = msg.tracks[0];
  EXPECT_EQ(msg.header.frame_id, "odom");
  EXPECT_EQ(t.track_id, 7u);
  EXPECT_EQ(t.id, 1);
  EXPECT_EQ(t.cameras, track.cameras);
  EXPECT_TRUE(t.validated);
  EXPECT_EQ(t.hits, 12u);
  EXPECT_EQ(t.misses, 2u);
  EXPECT_EQ(t.outliers, 1u);
  EXPECT_DOUBLE_EQ(t.age, 0.8);
  EXPECT_NEAR(t.last_seen.toSec(), 100.25, 1e-6);
  EXPECT_TRUE(t.filtered);
  EXPECT_DOUBLE_EQ(t.pose.pose.position.x, 7.6);
  EXPECT_NEAR(t.pose.pose.orientation.z, std::sin(0.25), 1e-12);
  for (int i = 0; i < 36; ++i) EXPECT_DOUBLE_EQ(t.pose.covariance[i], track.covariance.val[i]);

  const visualization_msgs::MarkerArray markers = ToTrackMarkers(msg);
  ASSERT_EQ(markers.markers.size(), 5u);  // DELETEALL, then an ellipsoid and a label per track
  EXPECT_EQ(markers.markers[0].action, visualization_msgs::Marker::DELETEALL);
  const auto& ellipsoid = markers.markers[1];
  EXPECT_EQ(ellipsoid.type, visualization_msgs::Marker::SPHERE);
  EXPECT_EQ(ellipsoid.id, 7);
  // 3 sigma each way: 18, 12 and 6 cm across, largest first, the largest along the turned y axis.
  EXPECT_NEAR(ellipsoid.scale.x, 0.18, 1e-9);
  EXPECT_NEAR(ellipsoid.scale.y, 0.12, 1e-9);
  EXPECT_NEAR(ellipsoid.scale.z, 0.06, 1e-9);
  tf2::Quaternion q;
  tf2::fromMsg(ellipsoid.pose.orientation, q);
  const tf2::Vector3 largest = tf2::quatRotate(q, tf2::Vector3(1, 0, 0));
  EXPECT_NEAR(std::abs(largest.z()), 1.0, 1e-9) << "the 3 cm sigma is along z";
  const tf2::Vector3 middle = tf2::quatRotate(q, tf2::Vector3(0, 1, 0));
  EXPECT_NEAR(std::abs(middle.x() * -s + middle.y() * c), 1.0, 1e-9) << "the 2 cm sigma is along the turned y";
  EXPECT_GT(ellipsoid.color.g, ellipsoid.color.r);  // validated: green
  EXPECT_GT(markers.markers[3].color.r, markers.markers[3].color.g);  // not yet: orange
  EXPECT_EQ(markers.markers[2].text, "1 (12)");
}

}  // namespace
}  // namespace arucotag

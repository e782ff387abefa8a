// ToMessage's covariance, orientation and pattern-fit flags, without a master.
#include <cmath>

#include <gtest/gtest.h>
#include <opencv2/calib3d.hpp>
#include <tf2/LinearMath/Quaternion.h>
#include <tf2_geometry_msgs/tf2_geometry_msgs.h>

#include <arucotag/ros/conversions.hpp>

namespace arucotag {
namespace {

// A tag whose pose covariance has distinct position and rotation blocks and a cross term.
ArucoTag TagWithCovariance() {
  ArucoTag tag;
  tag.id = 4;
  tag.pose_source = PoseSource::kPnp;
  tag.rvec = cv::Vec3d(0.1, -0.2, 0.3);
  tag.tvec = cv::Vec3d(0.2, -0.1, 2.0);
  tag.orientation_measured = true;
  tag.covariance = PoseCovariance::zeros();
  const double diagonal[6] = {1e-6, 4e-6, 9e-4, 1e-4, 4e-4, 1e-5};
  for (int i = 0; i < 6; ++i) tag.covariance(i, i) = diagonal[i];
  tag.covariance(2, 3) = tag.covariance(3, 2) = 5e-6;
  return tag;
}

TEST(ToMessage, CovarianceInTheOpticalFrameIsTheCoresRowMajor) {
  const ArucoTag tag = TagWithCovariance();
  const ArucoTagMsg msg = ToMessage(tag);
  for (int i = 0; i < 36; ++i) EXPECT_DOUBLE_EQ(msg.covariance[i], tag.covariance.val[i]) << i;
  EXPECT_DOUBLE_EQ(msg.covariance[2 * 6 + 3], 5e-6);
  EXPECT_TRUE(msg.orientation_measured);
  EXPECT_FALSE(msg.pattern_fitted);
  ArucoTag fitted = tag;
  fitted.pattern_fitted = true;
  EXPECT_TRUE(ToMessage(fitted).pattern_fitted);

  ArucoTag none;
  const ArucoTagMsg empty = ToMessage(none);
  EXPECT_FALSE(empty.orientation_measured);
  EXPECT_TRUE(std::isnan(empty.covariance[0]));
}

// Into an output frame turned 90 degrees about z (x -> y): the optical x variance becomes the output
// y variance, for the position and for the rotation about that axis alike; the cross term follows.
TEST(ToMessage, CovarianceTurnsWithTheOutputFrame) {
  const ArucoTag tag = TagWithCovariance();
  geometry_msgs::TransformStamped to_output;
  to_output.header.frame_id = "base_link";
  tf2::Quaternion q;
  q.setRPY(0.0, 0.0, M_PI / 2.0);
  to_output.transform.rotation = tf2::toMsg(q);
  to_output.transform.translation.x = 1.0;
  std_msgs::Header header;
  header.frame_id = "camera_optical";
  const ArucoTagArray array = ToMessage({tag}, header, &to_output);
  ASSERT_EQ(array.tags.size(), 1u);
  const auto& c = array.tags[0].covariance;
  const auto at = [&](int i, int j) { return c[6 * i + j]; };
  EXPECT_NEAR(at(0, 0), 4e-6, 1e-15);  // output x = - optical y
  EXPECT_NEAR(at(1, 1), 1e-6, 1e-15);  // output y = optical x
  EXPECT_NEAR(at(2, 2), 9e-4, 1e-15);
  EXPECT_NEAR(at(3, 3), 4e-4, 1e-15);
  EXPECT_NEAR(at(4, 4), 1e-4, 1e-15);
  EXPECT_NEAR(at(5, 5), 1e-5, 1e-15);
  EXPECT_NEAR(at(2, 4), 5e-6, 1e-15);  // z with the rotation about output y (= optical x)
  EXPECT_NEAR(at(4, 2), 5e-6, 1e-15);
  EXPECT_NEAR(at(2, 3), 0.0, 1e-15);
  EXPECT_NEAR(array.tags[0].pose.position.x, 1.0 + 0.1, 1e-12);
  EXPECT_NEAR(array.tags[0].pose.position.y, 0.2, 1e-12);
}

// rviz's view of a bundle: every configured face where the bundle pose puts it, the name above it,
// after the DELETEALL that clears the previous frame's; a bundle missing from the config draws nothing.
TEST(ToBundleMarkers, FacesStandWhereTheBundlePosePutsThem) {
  const std::vector<MarkerBundle> config = BundlesFromText(R"({"bundles": [{"name": "post", "members": [
      {"id": 1, "size": 0.15, "position": [0.1, 0.0, 0.5], "rpy_deg": [90, 0, 90]},
      {"id": 2, "size": 0.2, "position": [0.0, 0.1, 0.5], "rpy_deg": [90, 0, 180]}]}]})");
  BundleArray array;
  array.header.frame_id = "odom";
  array.header.stamp = ros::Time(42, 5);
  Bundle post;
  post.name = "post";
  post.pose.pose.position.x = 7.0;
  post.pose.pose.position.y = -1.0;
  tf2::Quaternion q;
  q.setRPY(0.0, 0.0, M_PI / 2);  // the post turned a quarter turn: its +x is odom's +y
  post.pose.pose.orientation = tf2::toMsg(q);
  array.bundles.push_back(post);
  Bundle unknown = post;
  unknown.name = "not_configured";
  array.bundles.push_back(unknown);

  const visualization_msgs::MarkerArray markers = ToBundleMarkers(array, config);
  ASSERT_EQ(markers.markers.size(), 4u);  // DELETEALL, two faces, one label
  EXPECT_EQ(markers.markers[0].action, visualization_msgs::Marker::DELETEALL);
  for (const auto& m : markers.markers) {
    EXPECT_EQ(m.header.frame_id, "odom");
    EXPECT_EQ(m.header.stamp, array.header.stamp);
  }
  const auto& front = markers.markers[1];
  EXPECT_EQ(front.type, visualization_msgs::Marker::CUBE);
  EXPECT_NEAR(front.pose.position.x, 7.0, 1e-12);  // member x 0.1 turned onto odom y
  EXPECT_NEAR(front.pose.position.y, -0.9, 1e-12);
  EXPECT_NEAR(front.pose.position.z, 0.5, 1e-12);
  EXPECT_DOUBLE_EQ(front.scale.x, 0.15);
  // The face's normal (marker z) points along the bundle's +x, which is odom's +y.
  tf2::Quaternion face;
  tf2::fromMsg(front.pose.orientation, face);
  const tf2::Vector3 normal = tf2::quatRotate(face, tf2::Vector3(0, 0, 1));
  EXPECT_NEAR(normal.y(), 1.0, 1e-9);
  const auto& left = markers.markers[2];
  EXPECT_NEAR(left.pose.position.x, 6.9, 1e-12);  // member y 0.1 turned onto odom -x
  EXPECT_NEAR(left.pose.position.y, -1.0, 1e-12);
  EXPECT_DOUBLE_EQ(left.scale.y, 0.2);
  const auto& label = markers.markers[3];
  EXPECT_EQ(label.type, visualization_msgs::Marker::TEXT_VIEW_FACING);
  EXPECT_EQ(label.text, "post");
  EXPECT_NEAR(label.pose.position.z, 0.5 + 0.1 + 0.1, 1e-12);  // above the highest face's top edge
  EXPECT_NE(front.id, left.id);
}

}  // namespace
}  // namespace arucotag

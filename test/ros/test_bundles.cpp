// Rostest (bundles.test): config/urc_bundles.yaml through the shipped launch file into the real
// nodelet; a rendered post_1 must come out as one bundle pose matching the truth, in the optical
// frame, in ~output_frame, and as TF.
#include <tf2_ros/buffer.h>
#include <tf2_ros/static_transform_broadcaster.h>
#include <tf2_ros/transform_listener.h>

#include <arucotag/BundleArray.h>

#include "rig.hpp"

namespace arucotag::test {
namespace {

constexpr double kAzimuth = 40.0 * CV_PI / 180.0;  // camera direction from the front face towards the left one

struct Post {
  cv::Matx33d rotation;  // bundle -> optical
  cv::Vec3d position;    // bundle origin (the post's foot) in the optical frame
  std::vector<sim::Marker> markers;
};

// post_1 of config/urc_bundles.yaml (written out here, not parsed: the nodelet's reading of the
// file is under test) standing upright 2.5 m ahead, its markers near the image centre and its foot
// 0.5 m below them, turned so that its front and left faces show.
Post UrcPost() {
  Post post;
  const double s = std::sin(kAzimuth), c = std::cos(kAzimuth);
  // Columns: bundle x (out of the front face), y (out of the left face), z (up = optical -y).
  post.rotation = cv::Matx33d(-s, c, 0, 0, 0, -1, -c, -s, 0);
  post.position = cv::Vec3d(0.1, 0.45, 2.5);
  // id, azimuth of the face normal in the bundle frame: front +x, left +y, right -y.
  for (const auto& [id, azimuth_deg] : {std::pair<int, double>{1, 0.0}, {2, 90.0}, {3, -90.0}}) {
    const double a = azimuth_deg * CV_PI / 180.0;
    const cv::Vec3d normal(std::cos(a), std::sin(a), 0.0), right(-std::sin(a), std::cos(a), 0.0), up(0, 0, 1);
    const cv::Matx33d face(right[0], up[0], normal[0], right[1], up[1], normal[1], right[2], up[2], normal[2]);
    sim::Marker marker;
    marker.id = id;
    marker.side = 0.15;
    cv::Rodrigues(post.rotation * face, marker.rvec);
    marker.tvec = post.rotation * (0.10 * normal + cv::Vec3d(0.0, 0.0, 0.5)) + post.position;
    post.markers.push_back(marker);
  }
  return post;
}

cv::Matx66d Covariance(const boost::array<double, 36>& c) { return cv::Matx66d(c.data()); }

TEST(Bundles, PostPoseInOpticalAndOutputFramesAndTf) {
  ros::NodeHandle nh;
  Rig rig(nh);
  tf2_ros::StaticTransformBroadcaster static_tf;
  static_tf.sendTransform(BodyFromOpticalTf());
  tf2_ros::Buffer tf_buffer;
  tf2_ros::TransformListener tf_listener(tf_buffer);
  Collector<BundleArray> optical(nh, "/optical/bundles"), body(nh, "/body/bundles");

  const Post post = UrcPost();
  const Scene scene = Render(post.markers);
  const double range = cv::norm(post.position);

  const auto seen = rig.PublishUntil(scene, optical, {}, 30.0);
  ASSERT_TRUE(seen) << "no bundles from /optical";
  EXPECT_EQ(seen->header.frame_id, kOpticalFrame);
  EXPECT_EQ(seen->camera_frame_id, kOpticalFrame);
  ASSERT_EQ(seen->bundles.size(), 1u);
  const Bundle& b = seen->bundles[0];
  EXPECT_EQ(b.name, "post_1");
  EXPECT_EQ(b.child_frame_id, std::string(kOpticalFrame) + "/post_1");
  EXPECT_EQ(b.member_ids, (std::vector<int>{1, 2})) << "the front and left faces, the right one turned away";
  EXPECT_EQ(b.pose_source, Bundle::PNP);
  EXPECT_LT(b.reprojection_error, 0.3);
  EXPECT_TRUE(PoseMatches(b.pose.pose, post.rotation, post.position, range));
  EXPECT_TRUE(PoseMatches(b.camera_pose.pose, post.rotation, post.position, range));
  const cv::Matx66d covariance = Covariance(b.pose.covariance);
  for (int i = 0; i < 6; ++i) {
    EXPECT_GT(covariance(i, i), 0.0) << i;
    EXPECT_LT(covariance(i, i), 1e-4) << i << ": sigma below 1 cm, 0.6 deg";
  }

  geometry_msgs::TransformStamped tf;
  ASSERT_NO_THROW(tf = tf_buffer.lookupTransform(kOpticalFrame, b.child_frame_id, seen->header.stamp,
                                                 ros::Duration(3.0)));
  geometry_msgs::Pose from_tf;
  from_tf.position.x = tf.transform.translation.x;
  from_tf.position.y = tf.transform.translation.y;
  from_tf.position.z = tf.transform.translation.z;
  from_tf.orientation = tf.transform.rotation;
  EXPECT_TRUE(PoseMatches(from_tf, post.rotation, post.position, range));

  // ~output_frame: pose moved into the body frame, camera_pose left in the optical one, the
  // covariance turned with the frame (its trace per block unchanged).
  const auto moved = rig.PublishUntil(scene, body, {}, 20.0);
  ASSERT_TRUE(moved) << "no bundles from /body";
  EXPECT_EQ(moved->header.frame_id, kBodyFrame);
  EXPECT_EQ(moved->camera_frame_id, kOpticalFrame);
  ASSERT_EQ(moved->bundles.size(), 1u);
  const Bundle& m = moved->bundles[0];
  const cv::Matx33d r = BodyFromOpticalRotation();
  EXPECT_TRUE(PoseMatches(m.pose.pose, r * post.rotation, r * post.position + BodyFromOpticalTranslation(), range));
  EXPECT_TRUE(PoseMatches(m.camera_pose.pose, post.rotation, post.position, range));
  const cv::Matx66d in_body = Covariance(m.pose.covariance), in_optical = Covariance(m.camera_pose.covariance);
  for (int block = 0; block < 6; block += 3) {
    const double body_trace = in_body(block, block) + in_body(block + 1, block + 1) + in_body(block + 2, block + 2);
    const double optical_trace =
        in_optical(block, block) + in_optical(block + 1, block + 1) + in_optical(block + 2, block + 2);
    EXPECT_NEAR(body_trace, optical_trace, 1e-9 + 1e-6 * optical_trace) << block;
  }
  EXPECT_GT(std::abs(in_body(0, 0) - in_optical(0, 0)), 1e-12) << "the body frame's x is not the optical x";
}

}  // namespace
}  // namespace arucotag::test

int main(int argc, char** argv) {
  testing::InitGoogleTest(&argc, argv);
  ros::init(argc, argv, "test_ros_bundles");
  ros::AsyncSpinner spinner(2);
  spinner.start();
  ros::NodeHandle nh;  // keeps the node up between the tests' own handles
  const int result = RUN_ALL_TESTS();
  spinner.stop();
  return result;
}

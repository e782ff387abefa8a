// replay_pacer: republishes the stamp of every tag array as a geometry_msgs/PointStamped on
// `tags_stamp`, so `rosbag play --rate-control-topic` can hold playback while the detector lags.
// rosbag only reads the stamp of messages whose definition starts with a bare `Header header`
// line, which arucotag/ArucoTagArray (std_msgs/Header, after its comment) does not.
// launch/replay.launch starts it with rate_control:=true.
#include <arucotag/ros/messages.hpp>

#include <geometry_msgs/PointStamped.h>
#include <ros/ros.h>

int main(int argc, char** argv) {
  ros::init(argc, argv, "replay_pacer");
  ros::NodeHandle nh;
  ros::Publisher stamps = nh.advertise<geometry_msgs::PointStamped>("tags_stamp", 10);
  // The count of tags in x, for anyone watching the topic.
  ros::Subscriber tags = nh.subscribe<arucotag::ArucoTagArray>(
      "tags", 100, [&stamps](const arucotag::ArucoTagArrayConstPtr& array) {
        geometry_msgs::PointStamped out;
        out.header = array->header;
        out.point.x = static_cast<double>(array->tags.size());
        stamps.publish(out);
      });
  ros::spin();
  return 0;
}

// detector_node: the DetectorNodelet in a process of its own, for setups without a nodelet manager.
// Remappings and private parameters are the node's: `rosrun arucotag detector_node image:=... _tag_size:=0.2`.
#include <nodelet/loader.h>
#include <ros/ros.h>

int main(int argc, char** argv) {
  ros::init(argc, argv, "detector");
  nodelet::Loader loader(false);  // no load/unload services: this process hosts exactly one nodelet
  const nodelet::M_string remappings(ros::names::getRemappings());
  const nodelet::V_string args(argv + 1, argv + argc);
  if (!loader.load(ros::this_node::getName(), "arucotag/DetectorNodelet", remappings, args)) {
    ROS_FATAL("cannot load arucotag/DetectorNodelet: is the package built and its devel/install space sourced?");
    return 1;
  }
  ros::spin();
  return 0;
}

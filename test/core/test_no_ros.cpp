// The core must stay ROS-free: rover code and tests use it without a ROS install. PCL is not ROS: the
// core fits planes with its sample_consensus library, and pulls in no more of PCL than that.
#include <array>
#include <cstdio>
#include <memory>
#include <string>

#include <gtest/gtest.h>

namespace {

std::string Shell(const std::string& command) {
  std::string output;
  std::unique_ptr<FILE, int (*)(FILE*)> pipe(popen(command.c_str(), "r"), pclose);
  if (!pipe) return output;
  std::array<char, 512> buffer;
  while (fgets(buffer.data(), buffer.size(), pipe.get())) output += buffer.data();
  return output;
}

TEST(CoreIsRosFree, LinksNoRosLibrary) {
  const std::string deps = Shell(std::string("ldd ") + ARUCOTAG_CORE_LIBRARY);
  ASSERT_NE(deps.find("libopencv_aruco"), std::string::npos) << deps;
  ASSERT_NE(deps.find("libpcl_sample_consensus"), std::string::npos) << deps;
  for (const char* ros : {"libroscpp", "librosconsole", "libcv_bridge", "librostime", "libpcl_ros", "libtf2",
                          "libcpp_common", "libnodelet", "libimage_transport", "libvtk", "libpcl_io"}) {
    EXPECT_EQ(deps.find(ros), std::string::npos) << ros << " in\n" << deps;
  }
}

TEST(CoreIsRosFree, HeadersIncludeNoRos) {
  const std::string hits =
      Shell(std::string("grep -lE '#include <(ros|sensor_msgs|geometry_msgs|tf2|cv_bridge|pcl_conversions|pcl_ros)' ") + ARUCOTAG_SOURCE_DIR +
          "/include/arucotag/*.hpp " + ARUCOTAG_SOURCE_DIR + "/src/core/*.cpp 2>/dev/null");
  EXPECT_EQ(hits, "");
}

}  // namespace

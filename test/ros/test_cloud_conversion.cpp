// CloudFromMessage: PointCloud2 -> pcl::PointCloud through pcl::fromROSMsg, without a master.
#include <cmath>
#include <cstring>
#include <limits>
#include <string>

#include <gtest/gtest.h>
#include <sensor_msgs/PointField.h>

#include <arucotag/ros/conversions.hpp>

namespace arucotag {
namespace {

constexpr float kNan = std::numeric_limits<float>::quiet_NaN();

// A width x height cloud whose point (u, v) is (u, v, 10 + u + width * v), except (1, 0), a hole.
// One byte of padding before x, y, z (point_step 13: floats at odd addresses) and a 4-byte
// intensity field after them.
sensor_msgs::PointCloud2 Cloud(uint32_t width, uint32_t height) {
  sensor_msgs::PointCloud2 cloud;
  cloud.width = width;
  cloud.height = height;
  const char* names[4] = {"x", "y", "z", "intensity"};
  for (int i = 0; i < 4; ++i) {
    sensor_msgs::PointField field;
    field.name = names[i];
    field.offset = 1 + 4 * i;
    field.datatype = sensor_msgs::PointField::FLOAT32;
    field.count = 1;
    cloud.fields.push_back(field);
  }
  cloud.point_step = 17;
  cloud.row_step = width * cloud.point_step;
  cloud.data.assign(size_t{cloud.row_step} * height, 0);
  for (uint32_t v = 0; v < height; ++v) {
    for (uint32_t u = 0; u < width; ++u) {
      float xyz[3] = {float(u), float(v), float(10 + u + width * v)};
      if (u == 1 && v == 0) xyz[0] = xyz[1] = xyz[2] = kNan;
      std::memcpy(&cloud.data[v * cloud.row_step + u * cloud.point_step + 1], xyz, sizeof(xyz));
    }
  }
  return cloud;
}

std::string ErrorOf(const sensor_msgs::PointCloud2& cloud, const cv::Size& size) {
  try {
    CloudFromMessage(cloud, size);
  } catch (const Error& e) {
    return e.what();
  }
  return "";
}

TEST(CloudFromMessage, ReadsOddOffsetsAndKeepsHoles) {
  const auto points = CloudFromMessage(Cloud(4, 3), {4, 3});
  ASSERT_EQ(points.width, 4u);
  ASSERT_EQ(points.height, 3u);
  EXPECT_FLOAT_EQ(points.at(3, 2).x, 3.f);
  EXPECT_FLOAT_EQ(points.at(3, 2).y, 2.f);
  EXPECT_FLOAT_EQ(points.at(3, 2).z, 21.f);
  EXPECT_TRUE(std::isnan(points.at(1, 0).z));
}

TEST(CloudFromMessage, MovesPointsByTheTransform) {
  geometry_msgs::Transform transform;  // 90 degrees about z, then 1 m along x
  transform.rotation.z = transform.rotation.w = std::sqrt(0.5);
  transform.translation.x = 1.0;
  const auto points = CloudFromMessage(Cloud(4, 3), {4, 3}, &transform);
  // (3, 2, 21) -> (-2, 3, 21) -> (-1, 3, 21)
  EXPECT_NEAR(points.at(3, 2).x, -1.f, 1e-5);
  EXPECT_NEAR(points.at(3, 2).y, 3.f, 1e-5);
  EXPECT_NEAR(points.at(3, 2).z, 21.f, 1e-5);
  EXPECT_TRUE(std::isnan(points.at(1, 0).x));
}

TEST(CloudFromMessage, EnlargesACloudSmallerByAWholeFactor) {
  const auto points = CloudFromMessage(Cloud(4, 3), {8, 6});
  ASSERT_EQ(points.width, 8u);
  ASSERT_EQ(points.height, 6u);
  // Image pixels (6..7, 4..5) all see cloud point (3, 2).
  for (int v = 4; v < 6; ++v) {
    for (int u = 6; u < 8; ++u) EXPECT_FLOAT_EQ(points.at(u, v).z, 21.f) << u << "," << v;
  }
  EXPECT_TRUE(std::isnan(points.at(3, 1).z));  // the hole covers its block
  EXPECT_FLOAT_EQ(points.at(0, 0).z, 10.f);
}

TEST(CloudFromMessage, RejectsWhatFromRosMsgWouldMisread) {
  EXPECT_EQ(ErrorOf(Cloud(4, 3), {6, 3}),
            "point cloud is 4x3 but the image is 6x3; an organized cloud must match the image pixel for pixel or be "
            "it downscaled by a whole factor");
  auto no_y = Cloud(4, 3);
  no_y.fields.erase(no_y.fields.begin() + 1);
  EXPECT_EQ(ErrorOf(no_y, {4, 3}), "point cloud has no 'y' field");
  auto doubles = Cloud(4, 3);
  doubles.fields[2].datatype = sensor_msgs::PointField::FLOAT64;
  EXPECT_EQ(ErrorOf(doubles, {4, 3}), "point cloud field 'z' is not a single float32");
  auto short_buffer = Cloud(4, 3);
  short_buffer.data.resize(short_buffer.data.size() - 1);
  EXPECT_EQ(ErrorOf(short_buffer, {4, 3}), "point cloud buffer is shorter than 4x3 points of 17 bytes");
  auto narrow = Cloud(4, 3);
  narrow.point_step = 12;
  narrow.row_step = 4 * 12;
  EXPECT_EQ(ErrorOf(narrow, {4, 3}), "point cloud field 'z' lies beyond point_step");  // 9 + 4 > 12
  auto row = Cloud(12, 1);
  EXPECT_EQ(ErrorOf(row, {12, 1}), "point cloud is not organized (12x1); an organized cloud has one point per image pixel");
}

}  // namespace
}  // namespace arucotag

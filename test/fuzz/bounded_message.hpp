#pragma once

// ROS messages deserialized from untrusted bytes without trusting their length prefixes.
// ros::serialization resizes a vector to its claimed length before it reads the elements (a
// 4-byte prefix of 0xffffffff allocates 4 GB, then throws), so each message's layout is walked
// first and every array and string length checked against the bytes that remain. Only then does
// ros::serialization read it, and its allocations are bounded by the input's size.
#include <cstddef>
#include <cstdint>
#include <cstring>

#include <dynamic_reconfigure/Config.h>
#include <ros/serialization.h>
#include <sensor_msgs/CameraInfo.h>
#include <sensor_msgs/CompressedImage.h>
#include <sensor_msgs/Image.h>
#include <sensor_msgs/PointCloud2.h>

namespace arucotag::fuzz {

class LayoutCheck {
 public:
  LayoutCheck(const std::uint8_t* data, std::size_t size) : data_(data), size_(size) {}

  bool Fixed(std::size_t bytes) {
    if (!ok_ || size_ - at_ < bytes) return ok_ = false;
    at_ += bytes;
    return true;
  }
  /// A length prefix, checked as `element_bytes` bytes per element (a lower bound for variable
  /// elements, which check their own contents after). Returns the count, 0 when it does not fit.
  std::uint32_t Length(std::size_t element_bytes) {
    std::uint32_t n = 0;
    if (!ok_ || size_ - at_ < 4) return ok_ = false, 0;
    std::memcpy(&n, data_ + at_, 4);
    at_ += 4;
    if (element_bytes && n > (size_ - at_) / element_bytes) return ok_ = false, 0;
    if (!element_bytes && n > size_) return ok_ = false, 0;  // empty elements: bound the loop anyway
    return n;
  }
  bool String() { return Fixed(Length(1)); }
  bool Array(std::size_t element_bytes) { return Fixed(Length(element_bytes) * element_bytes); }
  bool ok() const { return ok_; }

 private:
  const std::uint8_t* data_;
  std::size_t size_;
  std::size_t at_ = 0;
  bool ok_ = true;
};

inline bool Header(LayoutCheck& c) { return c.Fixed(4 + 8) && c.String(); }

inline bool Layout(LayoutCheck& c, const sensor_msgs::Image*) {
  return Header(c) && c.Fixed(8) && c.String() && c.Fixed(1 + 4) && c.Array(1);
}
inline bool Layout(LayoutCheck& c, const sensor_msgs::CompressedImage*) {
  return Header(c) && c.String() && c.Array(1);
}
inline bool Layout(LayoutCheck& c, const sensor_msgs::CameraInfo*) {
  // height, width, distortion_model, D[], K, R, P, binning_x, binning_y, roi
  return Header(c) && c.Fixed(8) && c.String() && c.Array(8) && c.Fixed(8 * (9 + 9 + 12)) && c.Fixed(8) &&
         c.Fixed(4 * 4 + 1);
}
inline bool Layout(LayoutCheck& c, const sensor_msgs::PointCloud2*) {
  if (!Header(c) || !c.Fixed(8)) return false;
  const std::uint32_t fields = c.Length(4 + 4 + 1 + 4);  // name, offset, datatype, count
  for (std::uint32_t i = 0; i < fields && c.ok(); ++i) c.String() && c.Fixed(4 + 1 + 4);
  return c.ok() && c.Fixed(1 + 4 + 4) && c.Array(1) && c.Fixed(1);
}
inline bool Layout(LayoutCheck& c, const dynamic_reconfigure::Config*) {
  const std::uint32_t bools = c.Length(4 + 1);
  for (std::uint32_t i = 0; i < bools && c.ok(); ++i) c.String() && c.Fixed(1);
  const std::uint32_t ints = c.Length(4 + 4);
  for (std::uint32_t i = 0; i < ints && c.ok(); ++i) c.String() && c.Fixed(4);
  const std::uint32_t strs = c.Length(4 + 4);
  for (std::uint32_t i = 0; i < strs && c.ok(); ++i) c.String() && c.String();
  const std::uint32_t doubles = c.Length(4 + 8);
  for (std::uint32_t i = 0; i < doubles && c.ok(); ++i) c.String() && c.Fixed(8);
  const std::uint32_t groups = c.Length(4 + 1 + 4 + 4);  // name, state, id, parent
  for (std::uint32_t i = 0; i < groups && c.ok(); ++i) c.String() && c.Fixed(1 + 4 + 4);
  return c.ok();
}

/// Fills `message` from `data` when its layout fits in `size` bytes; false (message untouched)
/// otherwise. Trailing bytes are allowed, as ROS allows them.
template <class Message>
bool Deserialize(const std::uint8_t* data, std::size_t size, Message& message) {
  LayoutCheck check(data, size);
  if (!Layout(check, static_cast<const Message*>(nullptr))) return false;
  ros::serialization::IStream stream(const_cast<std::uint8_t*>(data), static_cast<std::uint32_t>(size));
  ros::serialization::deserialize(stream, message);
  return true;
}

}  // namespace arucotag::fuzz

// libFuzzer harness: the nodelet's conversions of untrusted messages. The first byte picks the
// message type (Image, CompressedImage, CameraInfo, PointCloud2) and a few options; the rest is
// the message as it would arrive on the wire, deserialized with ros::serialization (after a
// layout check that keeps length prefixes within the input: bounded_message.hpp). Every encoding,
// step, size, jpeg/png header, distortion model, ROI and field layout the bytes spell must give a
// result or an arucotag::Error.
#include <arucotag/ros/conversions.hpp>
#include <arucotag/ros/image_input.hpp>

#include <algorithm>
#include <cmath>
#include <cstddef>
#include <cstdint>

#include <boost/make_shared.hpp>

#include "bounded_message.hpp"

namespace {

// A tag in the middle of a 640x480 frame, scaled onto the image at hand.
arucotag::ArucoTag TagIn(const cv::Size& size) {
  arucotag::ArucoTag tag;
  tag.id = 1;
  const float sx = size.width / 640.f, sy = size.height / 480.f;
  tag.corners = {{{260 * sx, 180 * sy}, {380 * sx, 180 * sy}, {380 * sx, 300 * sy}, {260 * sx, 300 * sy}}};
  return tag;
}

void Image(const std::uint8_t* data, std::size_t size) {
  auto image = boost::make_shared<sensor_msgs::Image>();
  if (!arucotag::fuzz::Deserialize(data, size, *image)) return;
  try {
    const arucotag::DetectorImage input = arucotag::DetectorImageFrom(image);
    cv::Mat grey;
    arucotag::PreprocessFrame(input.pixels, grey, {input.format});
  } catch (const arucotag::Error&) {
  }
  try {
    (void)arucotag::OverlayBgr8(image);
  } catch (const arucotag::Error&) {
  }
}

void Compressed(const std::uint8_t* data, std::size_t size) {
  sensor_msgs::CompressedImage compressed;
  if (!arucotag::fuzz::Deserialize(data, size, compressed)) return;
  try {
    const arucotag::DetectorImage input = arucotag::DetectorImageFrom(compressed);
    cv::Mat grey;
    arucotag::PreprocessFrame(input.pixels, grey, {input.format});
  } catch (const arucotag::Error&) {
  }
}

void CameraInfo(std::uint8_t options, const std::uint8_t* data, std::size_t size) {
  sensor_msgs::CameraInfo info;
  if (!arucotag::fuzz::Deserialize(data, size, info)) return;
  // The image it is paired with: the size the info states, or (sometimes) another one.
  const cv::Size image_size = (options & 2) ? cv::Size(640, 480)
                                            : cv::Size(static_cast<int>(info.width & 0xffff),
                                                       static_cast<int>(info.height & 0xffff));
  try {
    const arucotag::CameraModel camera = arucotag::CameraModelFromInfo(info, options & 1, image_size);
    arucotag::ArucoTag tag = TagIn(image_size);
    arucotag::EstimatePoseFromPNP(camera, tag);
  } catch (const arucotag::Error&) {
  }
}

void Cloud(std::uint8_t options, const std::uint8_t* data, std::size_t size) {
  sensor_msgs::PointCloud2 cloud;
  if (!arucotag::fuzz::Deserialize(data, size, cloud)) return;
  geometry_msgs::Transform transform;
  transform.translation.x = 0.1;
  transform.rotation.z = std::sqrt(0.5);
  transform.rotation.w = std::sqrt(0.5);
  try {
    // The image the cloud goes with: the cloud's own size, or twice it (a half-resolution cloud).
    const int factor = (options & 2) ? 2 : 1;
    const cv::Size image_size(static_cast<int>(std::min<std::uint32_t>(cloud.width, 4096)) * factor,
                              static_cast<int>(std::min<std::uint32_t>(cloud.height, 4096)) * factor);
    const auto points = arucotag::CloudFromMessage(cloud, image_size, (options & 1) ? &transform : nullptr);
    arucotag::ArucoTag tag = TagIn(image_size);
    arucotag::EstimatePoseFromPointCloud(points, tag);
  } catch (const arucotag::Error&) {
  }
}

}  // namespace

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  if (size < 1) return 0;
  const std::uint8_t selector = data[0];
  const std::uint8_t options = selector >> 2;
  switch (selector & 3) {
    case 0:
      Image(data + 1, size - 1);
      break;
    case 1:
      Compressed(data + 1, size - 1);
      break;
    case 2:
      CameraInfo(options, data + 1, size - 1);
      break;
    default:
      Cloud(options, data + 1, size - 1);
      break;
  }
  return 0;
}

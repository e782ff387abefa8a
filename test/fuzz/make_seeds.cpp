// Writes the starting seeds of test/fuzz/corpus/<harness>/seed_*: real inputs each harness reads
// the way its LLVMFuzzerTestOneInput does (the header bytes mirror FuzzInput's reads). Run once by
// hand from the fuzz build (scripts/fuzz.sh builds it); the fuzzer grows the corpus from them.
//   fuzz_make_seeds <source dir>/test/fuzz/corpus <source dir>/test/data
#include <cstdint>
#include <fstream>
#include <iostream>
#include <string>
#include <vector>

#include <camera_calibration_parsers/parse.h>
#include <dynamic_reconfigure/Config.h>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>
#include <ros/serialization.h>
#include <sensor_msgs/CameraInfo.h>
#include <sensor_msgs/CompressedImage.h>
#include <sensor_msgs/Image.h>
#include <sensor_msgs/PointCloud2.h>
#include <sensor_msgs/distortion_models.h>
#include <sensor_msgs/point_cloud2_iterator.h>

#include <arucotag/ros/parameters.hpp>
#include <arucotag/sim.hpp>

namespace {

using Bytes = std::vector<std::uint8_t>;

// The writing side of FuzzInput.
struct Writer {
  Bytes bytes;
  Writer& Byte(std::uint8_t b) {
    bytes.push_back(b);
    return *this;
  }
  Writer& Int(int value, int lo) {
    const auto v = static_cast<std::uint16_t>(value - lo);
    return Byte(v & 0xff).Byte(v >> 8);
  }
  Writer& One() { return Byte(5); }  // FuzzInput::Double's special value 1.0
  Writer& Typical() { return Byte(100).Byte(0).Byte(0x20); }  // typical * 1.0
  Writer& Append(const Bytes& more) {
    bytes.insert(bytes.end(), more.begin(), more.end());
    return *this;
  }
};

std::string g_corpus;
void Write(const std::string& harness, const std::string& name, const Bytes& bytes) {
  const std::string path = g_corpus + "/" + harness + "/seed_" + name;
  std::ofstream(path, std::ios::binary).write(reinterpret_cast<const char*>(bytes.data()), bytes.size());
  std::cout << path << " " << bytes.size() << " bytes\n";
}

template <class Message>
Bytes Serialize(std::uint8_t selector, const Message& message) {
  Bytes bytes(1 + ros::serialization::serializationLength(message));
  bytes[0] = selector;
  ros::serialization::OStream stream(bytes.data() + 1, static_cast<std::uint32_t>(bytes.size() - 1));
  ros::serialization::serialize(stream, message);
  return bytes;
}

// Marker 3 of DICT_4X4_50 filling about half of a w x h frame, slightly turned.
cv::Mat Scene(cv::Size size, bool colour) {
  const arucotag::sim::Camera camera = arucotag::sim::MakeCamera(size, 60.0);
  arucotag::sim::RenderOptions options;
  options.colour = colour;
  options.supersample = 4;
  const double side = 0.15, distance = side / (0.5 * 2 * std::tan(30.0 * CV_PI / 180.0));
  return arucotag::sim::RenderScene(camera, {arucotag::sim::FacingCamera(3, side, {0.01, 0.0, distance}, 15.0)},
                                    options);
}

Bytes Pixels(const cv::Mat& image) {
  const cv::Mat c = image.isContinuous() ? image : image.clone();
  return Bytes(c.datastart, c.dataend);
}

void CoreSeeds() {
  // rows, cols, type index (kTypes), format (kFormats), flags, clahe clip, tile, sigma, dictionary,
  // refinement (kRefinements), extra tags, pixels.
  const auto header = [](int rows, int cols, int type_index, int flags, int refinement) {
    Writer w;
    w.Int(rows, 0).Int(cols, 0).Byte(type_index).Byte(0).Byte(flags).One().Int(8, -2);
    if (flags & 2) w.One();
    w.One().Byte(0).Byte(refinement).Int(0, 0);
    return w;
  };
  Write("core", "grey_96", header(96, 96, 0, 0, 4).Append(Pixels(Scene({96, 96}, false))).bytes);
  Write("core", "bgr_64_subpix", header(48, 64, 1, 0, 1).Append(Pixels(Scene({64, 48}, true))).bytes);
  // CLAHE and unsharp on, full search (no fast path), grey marker read as 16-bit samples.
  Write("core", "grey_80_preprocess", header(80, 80, 0, 1 | 2 | 4, 4).Append(Pixels(Scene({80, 80}, false))).bytes);
  cv::Mat wide;
  Scene({64, 48}, false).convertTo(wide, CV_16U, 16.0);
  Write("core", "mono16_64", header(48, 64, 3, 0, 4).Append(Pixels(wide)).bytes);
}

void PoseSeeds() {
  // mode, camera (which K entries, kind), tag (half side, wild, side flag), cloud (kind, size, z0,
  // tilt, one noise byte per point), then arbitrary results (all zero here).
  for (int mode : {0, 2}) {
    // kind: bit 0 fisheye, then the index into kDistortionCounts: none, 5 plumb_bob, 4 fisheye.
    for (int kind : {0, 2 << 1, 1 << 1 | 1}) {
      Writer w;
      w.Byte(mode).Byte(0).Byte(kind);
      const int count = kind == 0 ? 0 : (kind & 1) ? 4 : 5;
      for (int i = 0; i < count; ++i) w.Byte(100).Byte(0).Byte(i % 2 ? 0x02 : 0xfe);  // +-0.0625 * 0.1
      w.Int(60, 0).Byte(0).Byte(0);
      w.Byte(0).Int(64, 0).Int(48, 0).Byte(128).Int(20, -100);
      w.Append(Bytes(64 * 48, 0));
      Write("pose", "mode" + std::to_string(mode) + "_lens" + std::to_string(kind), w.bytes);
    }
  }
}

void RosSeeds(const std::string& data_dir) {
  const cv::Mat grey = Scene({64, 48}, false), bgr = Scene({64, 48}, true);
  std_msgs::Header header;
  header.frame_id = "camera_optical";
  header.stamp = ros::Time(1700000000, 5);
  const auto image = [&](const cv::Mat& pixels, const std::string& encoding) {
    sensor_msgs::Image msg;
    msg.header = header;
    msg.height = pixels.rows;
    msg.width = pixels.cols;
    msg.encoding = encoding;
    msg.step = static_cast<std::uint32_t>(pixels.cols * pixels.elemSize());
    msg.data = Pixels(pixels);
    return Serialize(0, msg);
  };
  Write("ros", "image_mono8", image(grey, "mono8"));
  Write("ros", "image_bgr8", image(bgr, "bgr8"));
  Write("ros", "image_bayer_rggb8", image(grey, "bayer_rggb8"));
  cv::Mat uyvy(grey.rows, grey.cols, CV_8UC2);
  for (int v = 0; v < grey.rows; ++v)
    for (int u = 0; u < grey.cols; ++u) uyvy.at<cv::Vec2b>(v, u) = cv::Vec2b(128, grey.at<std::uint8_t>(v, u));
  Write("ros", "image_yuv422", image(uyvy, "yuv422"));
  cv::Mat wide;
  grey.convertTo(wide, CV_16U, 16.0);
  Write("ros", "image_mono16", image(wide, "mono16"));

  for (const std::string format : {"jpeg", "png"}) {
    sensor_msgs::CompressedImage msg;
    msg.header = header;
    msg.format = "bgr8; " + format + " compressed bgr8";
    cv::imencode("." + format, format == "png" ? grey : bgr, msg.data,
                 {format == "png" ? cv::IMWRITE_PNG_COMPRESSION : cv::IMWRITE_JPEG_QUALITY, format == "png" ? 9 : 60});
    Write("ros", "compressed_" + format, Serialize(1, msg));
  }

  std::string camera_name;
  sensor_msgs::CameraInfo info;
  if (!camera_calibration_parsers::readCalibration(data_dir + "/ubiquity_fiducials/camera.yaml", camera_name, info)) {
    throw std::runtime_error("cannot read camera.yaml");
  }
  info.header = header;
  Write("ros", "info_raspicam", Serialize(2, info));
  Write("ros", "info_raspicam_projection", Serialize(2 | 1 << 2, info));
  sensor_msgs::CameraInfo binned = info;
  binned.binning_x = binned.binning_y = 2;
  binned.roi.x_offset = 320;
  binned.roi.y_offset = 240;
  binned.roi.width = 640;
  binned.roi.height = 480;
  Write("ros", "info_binned_roi", Serialize(2, binned));
  sensor_msgs::CameraInfo fisheye = info;
  fisheye.distortion_model = sensor_msgs::distortion_models::EQUIDISTANT;
  fisheye.D = {0.05, -0.01, 0.002, -0.0005};
  Write("ros", "info_equidistant", Serialize(2, fisheye));
  sensor_msgs::CameraInfo rational = info;
  rational.distortion_model = sensor_msgs::distortion_models::RATIONAL_POLYNOMIAL;
  rational.D = {0.1, -0.2, 0.001, 0.002, 0.01, 0.05, -0.01, 0.002};
  Write("ros", "info_rational", Serialize(2, rational));

  // An organized 16x12 cloud of a plane 1.5 m away, xyz + rgb, with a few holes.
  sensor_msgs::PointCloud2 cloud;
  cloud.header = header;
  sensor_msgs::PointCloud2Modifier modifier(cloud);
  modifier.setPointCloud2FieldsByString(2, "xyz", "rgb");
  modifier.resize(16 * 12);
  cloud.height = 12;
  cloud.width = 16;
  cloud.row_step = cloud.width * cloud.point_step;
  cloud.is_dense = false;
  sensor_msgs::PointCloud2Iterator<float> x(cloud, "x"), y(cloud, "y"), z(cloud, "z");
  for (int v = 0; v < 12; ++v) {
    for (int u = 0; u < 16; ++u, ++x, ++y, ++z) {
      const bool hole = (u * 7 + v * 3) % 11 == 0;
      *z = hole ? std::numeric_limits<float>::quiet_NaN() : 1.5f + 0.01f * u;
      *x = (u - 7.5f) * *z / 14.f;
      *y = (v - 5.5f) * *z / 14.f;
    }
  }
  Write("ros", "cloud_xyzrgb", Serialize(3, cloud));
  Write("ros", "cloud_xyzrgb_transformed", Serialize(3 | 1 << 2, cloud));
}

void ConfigSeeds() {
  for (const std::string name : {"DICT_4X4_50", "DICT_APRILTAG_36h11", "edge", "bgr8"}) {
    Writer w;
    w.Byte(0).Byte(static_cast<std::uint8_t>(name.size())).Append(Bytes(name.begin(), name.end()));
    Write("config", "name_" + name, w.bytes);
  }
  dynamic_reconfigure::Config message;
  arucotag::ToReconfigure({}, {}).__toMessage__(message);
  Write("config", "reconfigure_defaults", Serialize(1, message));
  Write("config", "values_defaults", Bytes{2});
}

}  // namespace

int main(int argc, char** argv) {
  if (argc != 3) {
    std::cerr << "usage: fuzz_make_seeds <test/fuzz/corpus> <test/data>\n";
    return 2;
  }
  g_corpus = argv[1];
  CoreSeeds();
  PoseSeeds();
  RosSeeds(argv[2]);
  ConfigSeeds();
  return 0;
}

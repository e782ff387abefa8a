#include <arucotag/ros/image_input.hpp>

#include <algorithm>
#include <climits>
#include <cstdint>
#include <exception>
#include <iterator>
#include <vector>

#include <opencv2/imgproc.hpp>
#include <sensor_msgs/image_encodings.h>

#include <arucotag/aruco_tag.hpp>

namespace arucotag {

namespace {

namespace enc = sensor_msgs::image_encodings;

constexpr int kNoConversion = -1;

// How one encoding reaches the detector and the overlay. The conversions are cv::cvtColor's codes
// rather than cv_bridge::cvtColor: cv_bridge scales 16 bits to 8 by 1/257 (a full-scale 12-bit red
// bayer_rggb16 comes out as bgr8 (0, 0, 16)), refuses 8UC1 to bgr8, and Debian's does not know
// yuv422_yuy2; one table serves both outputs.
struct Encoding {
  const char* name;
  int type;            // OpenCV type of the message's pixels
  PixelFormat shared;  // the format PreprocessFrame reads in place; kAuto: convert with to_grey
  int to_grey;         // cv::COLOR_* code to the detector's mono image, when not shared
  int to_bgr;          // cv::COLOR_* code to bgr for the overlay (after 16-bit scaling), or none
};

// OpenCV names a Bayer pattern after the second row's second and third pixels, ROS after the first
// two rows' first two: ROS rggb (R G / G B) is OpenCV's BG, and so on. test_encodings.cpp checks
// each against a mosaic of known colours.
const Encoding kEncodings[] = {
    {"mono8", CV_8UC1, PixelFormat::kMono8, kNoConversion, cv::COLOR_GRAY2BGR},
    {"8UC1", CV_8UC1, PixelFormat::kMono8, kNoConversion, cv::COLOR_GRAY2BGR},
    {"mono16", CV_16UC1, PixelFormat::kMono16, kNoConversion, cv::COLOR_GRAY2BGR},
    {"16UC1", CV_16UC1, PixelFormat::kMono16, kNoConversion, cv::COLOR_GRAY2BGR},
    {"bgr8", CV_8UC3, PixelFormat::kBgr8, kNoConversion, kNoConversion},
    {"8UC3", CV_8UC3, PixelFormat::kBgr8, kNoConversion, kNoConversion},
    {"rgb8", CV_8UC3, PixelFormat::kRgb8, kNoConversion, cv::COLOR_RGB2BGR},
    {"bgra8", CV_8UC4, PixelFormat::kBgra8, kNoConversion, cv::COLOR_BGRA2BGR},
    {"8UC4", CV_8UC4, PixelFormat::kBgra8, kNoConversion, cv::COLOR_BGRA2BGR},
    {"rgba8", CV_8UC4, PixelFormat::kRgba8, kNoConversion, cv::COLOR_RGBA2BGR},
    {"bgr16", CV_16UC3, PixelFormat::kAuto, cv::COLOR_BGR2GRAY, kNoConversion},
    {"rgb16", CV_16UC3, PixelFormat::kAuto, cv::COLOR_RGB2GRAY, cv::COLOR_RGB2BGR},
    {"bgra16", CV_16UC4, PixelFormat::kAuto, cv::COLOR_BGRA2GRAY, cv::COLOR_BGRA2BGR},
    {"rgba16", CV_16UC4, PixelFormat::kAuto, cv::COLOR_RGBA2GRAY, cv::COLOR_RGBA2BGR},
    {"yuv422", CV_8UC2, PixelFormat::kAuto, cv::COLOR_YUV2GRAY_UYVY, cv::COLOR_YUV2BGR_UYVY},
    // Not in Debian's sensor_msgs or cv_bridge; newer ROS releases name YUYV this way.
    {"yuv422_yuy2", CV_8UC2, PixelFormat::kAuto, cv::COLOR_YUV2GRAY_YUY2, cv::COLOR_YUV2BGR_YUY2},
    {"bayer_rggb8", CV_8UC1, PixelFormat::kAuto, cv::COLOR_BayerBG2GRAY, cv::COLOR_BayerBG2BGR},
    {"bayer_bggr8", CV_8UC1, PixelFormat::kAuto, cv::COLOR_BayerRG2GRAY, cv::COLOR_BayerRG2BGR},
    {"bayer_gbrg8", CV_8UC1, PixelFormat::kAuto, cv::COLOR_BayerGR2GRAY, cv::COLOR_BayerGR2BGR},
    {"bayer_grbg8", CV_8UC1, PixelFormat::kAuto, cv::COLOR_BayerGB2GRAY, cv::COLOR_BayerGB2BGR},
    {"bayer_rggb16", CV_16UC1, PixelFormat::kAuto, cv::COLOR_BayerBG2GRAY, cv::COLOR_BayerBG2BGR},
    {"bayer_bggr16", CV_16UC1, PixelFormat::kAuto, cv::COLOR_BayerRG2GRAY, cv::COLOR_BayerRG2BGR},
    {"bayer_gbrg16", CV_16UC1, PixelFormat::kAuto, cv::COLOR_BayerGR2GRAY, cv::COLOR_BayerGR2BGR},
    {"bayer_grbg16", CV_16UC1, PixelFormat::kAuto, cv::COLOR_BayerGB2GRAY, cv::COLOR_BayerGB2BGR},
};

const Encoding* FindEncoding(const std::string& name) {
  for (const auto& encoding : kEncodings) {
    if (name == encoding.name) return &encoding;
  }
  return nullptr;
}

std::string Describe(const sensor_msgs::Image& image) {
  return image.encoding + " image " + std::to_string(image.width) + "x" + std::to_string(image.height);
}

// Everything the conversions read is checked here, in 64-bit arithmetic, before any of it is used.
const Encoding& Validate(const sensor_msgs::Image& image) {
  const Encoding* encoding = FindEncoding(image.encoding);
  if (!encoding) {
    throw Error("unsupported image encoding '" + image.encoding + "' (supported: " + SupportedImageEncodings() + ")");
  }
  if (image.width == 0 || image.height == 0) throw Error(Describe(image) + " is empty");
  if (image.width > INT_MAX || image.height > INT_MAX) throw Error(Describe(image) + " is larger than OpenCV can hold");
  const std::uint64_t sample_bytes = CV_ELEM_SIZE1(encoding->type);
  const std::uint64_t row_bytes = std::uint64_t{image.width} * CV_ELEM_SIZE(encoding->type);
  if (image.step < row_bytes) {
    throw Error(Describe(image) + ": step " + std::to_string(image.step) + " is shorter than a row of " +
                std::to_string(row_bytes) + " bytes");
  }
  if (image.step % sample_bytes != 0) {
    throw Error(Describe(image) + ": step " + std::to_string(image.step) + " is not a whole number of " +
                std::to_string(sample_bytes) + "-byte samples");
  }
  const std::uint64_t needed = std::uint64_t{image.step} * image.height;
  if (image.data.size() < needed) {
    throw Error(Describe(image) + " with step " + std::to_string(image.step) + " needs " + std::to_string(needed) +
                " bytes but the message holds " + std::to_string(image.data.size()));
  }
  if (sample_bytes == 2 && image.is_bigendian) {
    throw Error(Describe(image) + " is big-endian; only little-endian 16-bit samples are supported");
  }
  if (encoding->type == CV_8UC2 && image.width % 2 != 0) {
    throw Error(Describe(image) + " has an odd width: packed 4:2:2 stores pixels in pairs");
  }
  return *encoding;
}

// A view of a validated message's pixels, for conversions that copy out of it at once.
cv::Mat View(const sensor_msgs::Image& image, const Encoding& encoding) {
  return cv::Mat(static_cast<int>(image.height), static_cast<int>(image.width), encoding.type,
                 const_cast<std::uint8_t*>(image.data.data()), image.step);
}

// OpenCV reports what it cannot convert (a Bayer image too small to demosaic, say) as cv::Exception;
// callers get it as an Error naming the encoding like every other refusal.
template <typename Convert>
auto Guarded(const sensor_msgs::Image& image, Convert convert) -> decltype(convert()) {
  try {
    return convert();
  } catch (const Error&) {
    throw;
  } catch (const std::exception& e) {
    throw Error(Describe(image) + ": " + e.what());
  }
}

// What a decoded file is labelled: the original encoding when compressed_image_transport's format
// string names a single-channel one of the decoded depth (a Bayer mosaic stored as grey png),
// otherwise what the pixels are.
std::string DecodedEncoding(const cv::Mat& decoded, const std::string& format) {
  const std::string original = format.substr(0, format.find(';'));
  const Encoding* named = FindEncoding(original);
  if (named && named->type == decoded.type() && CV_MAT_CN(named->type) == 1) return original;
  switch (decoded.type()) {
    case CV_8UC1:
      return enc::MONO8;
    case CV_16UC1:
      return enc::MONO16;
    case CV_8UC3:
      return enc::BGR8;
    case CV_8UC4:
      return enc::BGRA8;
    case CV_16UC3:
      return enc::BGR16;
    case CV_16UC4:
      return enc::BGRA16;
    default:
      return "";
  }
}

std::uint32_t BigEndian(const std::vector<std::uint8_t>& data, std::size_t at, int bytes) {
  std::uint32_t value = 0;
  for (int i = 0; i < bytes; ++i) value = (value << 8) | data[at + i];
  return value;
}

// Width and height from a png's IHDR or a jpeg's start-of-frame segment, without decoding.
cv::Size2l FileImageSize(const std::vector<std::uint8_t>& data, const std::string& what) {
  static const std::uint8_t kPng[] = {0x89, 'P', 'N', 'G', '\r', '\n', 0x1a, '\n', 0, 0, 0, 13, 'I', 'H', 'D', 'R'};
  if (data.size() >= sizeof(kPng) && std::equal(std::begin(kPng), std::end(kPng), data.begin())) {
    if (data.size() < sizeof(kPng) + 8) throw Error(what + ": png header is cut short");
    return {BigEndian(data, 16, 4), BigEndian(data, 20, 4)};
  }
  if (data.size() < 4 || data[0] != 0xff || data[1] != 0xd8) throw Error(what + ": neither jpeg nor png data");
  // Segments: ff, marker, 16-bit length counting itself. Start-of-frame markers are c0-cf but for
  // c4 (Huffman tables), c8 (reserved) and cc (arithmetic coding).
  std::size_t at = 2;
  while (true) {
    if (at >= data.size() || data[at] != 0xff) throw Error(what + ": jpeg has no frame header");
    while (at < data.size() && data[at] == 0xff) ++at;  // fill bytes
    if (at >= data.size()) break;
    const std::uint8_t marker = data[at++];
    if ((marker >= 0xd0 && marker <= 0xd7) || marker == 0x01) continue;  // no length
    if (marker == 0xd9 || marker == 0xda || at + 2 > data.size()) break;  // end, or scan data before any frame
    const std::size_t length = BigEndian(data, at, 2);
    const bool frame = marker >= 0xc0 && marker <= 0xcf && marker != 0xc4 && marker != 0xc8 && marker != 0xcc;
    if (frame) {
      if (length < 7 || at + 7 > data.size()) break;
      return {BigEndian(data, at + 5, 2), BigEndian(data, at + 3, 2)};
    }
    if (length < 2) break;
    at += length;
  }
  throw Error(what + ": jpeg has no frame header");
}

}  // namespace

const std::string& SupportedImageEncodings() {
  static const std::string names = [] {
    std::string list;
    for (const auto& encoding : kEncodings) list += (list.empty() ? "" : ", ") + std::string(encoding.name);
    return list;
  }();
  return names;
}

DetectorImage DetectorImageFrom(const sensor_msgs::ImageConstPtr& image) {
  if (!image) throw Error("no image message");
  const Encoding& encoding = Validate(*image);
  return Guarded(*image, [&] {
    DetectorImage out;
    if (encoding.shared != PixelFormat::kAuto) {
      out.shared = cv_bridge::toCvShare(image);
      out.pixels = out.shared->image;
      out.format = encoding.shared;
    } else {
      cv::cvtColor(View(*image, encoding), out.pixels, encoding.to_grey);
      out.format = out.pixels.depth() == CV_16U ? PixelFormat::kMono16 : PixelFormat::kMono8;
    }
    return out;
  });
}

cv::Mat OverlayBgr8(const sensor_msgs::ImageConstPtr& image) {
  if (!image) throw Error("no image message");
  const Encoding& encoding = Validate(*image);
  return Guarded(*image, [&] {
    cv::Mat pixels = View(*image, encoding);
    if (pixels.depth() == CV_16U) {
      double max_value = 0.0;
      cv::minMaxLoc(pixels.reshape(1), nullptr, &max_value);
      cv::Mat scaled;
      pixels.convertTo(scaled, CV_8U, max_value > 0.0 ? 255.0 / max_value : 1.0);
      pixels = scaled;
    }
    cv::Mat bgr;
    if (encoding.to_bgr == kNoConversion) {
      bgr = pixels.data == image->data.data() ? pixels.clone() : pixels;
    } else {
      cv::cvtColor(pixels, bgr, encoding.to_bgr);
    }
    return bgr;
  });
}

sensor_msgs::ImagePtr DecodeCompressedImage(const sensor_msgs::CompressedImage& compressed, std::size_t max_pixels) {
  const std::string what = "compressed image (format '" + compressed.format + "')";
  if (compressed.data.empty()) throw Error(what + " is empty");
  const cv::Size2l size = FileImageSize(compressed.data, what);
  if (size.width <= 0 || size.height <= 0 ||
      static_cast<std::uint64_t>(size.width) * static_cast<std::uint64_t>(size.height) > max_pixels) {
    throw Error(what + " claims a " + std::to_string(size.width) + "x" + std::to_string(size.height) +
                " image; only 1 to " + std::to_string(max_pixels) + " pixels are decoded");
  }
  cv_bridge::CvImagePtr decoded;
  try {
    decoded = cv_bridge::toCvCopy(compressed);  // passthrough: the file's own channels and depth
  } catch (const std::exception& e) {
    throw Error(what + ": " + e.what());
  }
  // cv_bridge labels whatever imdecode returns, an empty image for corrupt data included.
  if (!decoded || decoded->image.empty() || decoded->image.total() != static_cast<std::size_t>(size.area())) {
    throw Error(what + ": cannot decode its " + std::to_string(compressed.data.size()) + " bytes");
  }
  decoded->encoding = DecodedEncoding(decoded->image, compressed.format);
  if (decoded->encoding.empty()) {
    throw Error(what + " decodes to OpenCV type " + std::to_string(decoded->image.type()) + ", not an image");
  }
  return decoded->toImageMsg();
}

DetectorImage DetectorImageFrom(const sensor_msgs::CompressedImage& compressed) {
  return DetectorImageFrom(DecodeCompressedImage(compressed));
}

}  // namespace arucotag

// Every image encoding the nodelet takes, made from real photos the way a camera would send them,
// must give the detector what bgr8 gives it; malformed messages must be refused by name. No ROS
// master: only messages and the functions of image_input.hpp.
#include <algorithm>
#include <cstdint>
#include <cstdio>
#include <functional>
#include <map>
#include <string>
#include <vector>

#include <boost/make_shared.hpp>
#include <gtest/gtest.h>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>

#include <arucotag/arucotag.hpp>
#include <arucotag/ros/image_input.hpp>

namespace arucotag {
namespace {

// Camera drivers may pad rows; every message here does, so step is never width * bytes per pixel.
constexpr int kRowPadding = 8;

cv::Mat LoadBgr(const std::string& relative) {
  const cv::Mat image = cv::imread(std::string(ARUCOTAG_TEST_DATA) + "/" + relative, cv::IMREAD_COLOR);
  EXPECT_FALSE(image.empty()) << relative;
  return image;
}

sensor_msgs::ImagePtr Message(const cv::Mat& pixels, const std::string& encoding) {
  auto image = boost::make_shared<sensor_msgs::Image>();
  image->encoding = encoding;
  image->width = pixels.cols;
  image->height = pixels.rows;
  image->step = static_cast<uint32_t>(pixels.cols * pixels.elemSize() + kRowPadding);
  image->data.assign(static_cast<size_t>(image->step) * pixels.rows, 0xab);  // padding is garbage
  pixels.copyTo(cv::Mat(pixels.rows, pixels.cols, pixels.type(), image->data.data(), image->step));
  return image;
}

cv::Mat To16(const cv::Mat& pixels) {
  cv::Mat wide;
  pixels.convertTo(wide, CV_16U, 257.0);
  return wide;
}

// What the sensor behind a Bayer filter records: per cell only the channel its filter passes.
// `pattern` is the ROS name's letters, row by row ("rggb": R G on even rows, G B on odd ones).
cv::Mat Mosaic(const cv::Mat& bgr, const std::string& pattern) {
  const std::map<char, int> channel = {{'b', 0}, {'g', 1}, {'r', 2}};
  cv::Mat mosaic(bgr.size(), CV_8UC1);
  for (int y = 0; y < bgr.rows; ++y) {
    for (int x = 0; x < bgr.cols; ++x) {
      mosaic.at<uint8_t>(y, x) = bgr.at<cv::Vec3b>(y, x)[channel.at(pattern[2 * (y % 2) + x % 2])];
    }
  }
  return mosaic;
}

// BT.601 studio swing (Y 16-235, chroma 16-240), what UVC cameras send, chroma averaged over
// each pixel pair. uyvy: U Y0 V Y1 (ROS yuv422); otherwise Y0 U Y1 V (yuv422_yuy2).
cv::Vec3d Ycbcr(const cv::Vec3b& bgr) {
  const double b = bgr[0], g = bgr[1], r = bgr[2];
  return {16.0 + (65.481 * r + 128.553 * g + 24.966 * b) / 255.0,
          128.0 + (-37.797 * r - 74.203 * g + 112.0 * b) / 255.0,
          128.0 + (112.0 * r - 93.786 * g - 18.214 * b) / 255.0};
}

cv::Mat Yuv422(const cv::Mat& bgr, bool uyvy) {
  cv::Mat packed(bgr.rows, bgr.cols, CV_8UC2);
  for (int y = 0; y < bgr.rows; ++y) {
    for (int x = 0; x + 1 < bgr.cols; x += 2) {
      const cv::Vec3d a = Ycbcr(bgr.at<cv::Vec3b>(y, x)), b = Ycbcr(bgr.at<cv::Vec3b>(y, x + 1));
      const uint8_t y0 = cv::saturate_cast<uint8_t>(a[0]), y1 = cv::saturate_cast<uint8_t>(b[0]);
      const uint8_t u = cv::saturate_cast<uint8_t>((a[1] + b[1]) / 2), v = cv::saturate_cast<uint8_t>((a[2] + b[2]) / 2);
      uint8_t* out = packed.ptr<uint8_t>(y) + 2 * x;
      const uint8_t bytes[2][4] = {{y0, u, y1, v}, {u, y0, v, y1}};
      std::copy(bytes[uyvy], bytes[uyvy] + 4, out);
    }
  }
  return packed;
}

cv::Mat Convert(const cv::Mat& in, int code) {
  cv::Mat out;
  cv::cvtColor(in, out, code);
  return out;
}

// The photo as a camera publishing `encoding` would have sent it.
sensor_msgs::ImagePtr Encode(const cv::Mat& bgr, const std::string& encoding) {
  const cv::Mat grey = Convert(bgr, cv::COLOR_BGR2GRAY);
  const std::map<std::string, std::function<cv::Mat()>> make = {
      {"bgr8", [&] { return bgr; }},
      {"8UC3", [&] { return bgr; }},
      {"rgb8", [&] { return Convert(bgr, cv::COLOR_BGR2RGB); }},
      {"bgra8", [&] { return Convert(bgr, cv::COLOR_BGR2BGRA); }},
      {"8UC4", [&] { return Convert(bgr, cv::COLOR_BGR2BGRA); }},
      {"rgba8", [&] { return Convert(bgr, cv::COLOR_BGR2RGBA); }},
      {"mono8", [&] { return grey; }},
      {"8UC1", [&] { return grey; }},
      {"mono16", [&] { return To16(grey); }},
      {"16UC1", [&] { return To16(grey); }},
      {"bgr16", [&] { return To16(bgr); }},
      {"rgb16", [&] { return To16(Convert(bgr, cv::COLOR_BGR2RGB)); }},
      {"bgra16", [&] { return To16(Convert(bgr, cv::COLOR_BGR2BGRA)); }},
      {"rgba16", [&] { return To16(Convert(bgr, cv::COLOR_BGR2RGBA)); }},
      {"yuv422", [&] { return Yuv422(bgr, true); }},
      {"yuv422_yuy2", [&] { return Yuv422(bgr, false); }},
  };
  if (encoding.rfind("bayer_", 0) == 0) {
    const cv::Mat mosaic = Mosaic(bgr, encoding.substr(6, 4));
    return Message(encoding.back() == '6' ? To16(mosaic) : mosaic, encoding);
  }
  return Message(make.at(encoding)(), encoding);
}

const std::vector<std::string> kAllEncodings = {
    "bgr8",         "8UC3",         "rgb8",         "bgra8",        "8UC4",        "rgba8",
    "mono8",        "8UC1",         "mono16",       "16UC1",        "bgr16",       "rgb16",
    "bgra16",       "rgba16",       "yuv422",       "yuv422_yuy2",  "bayer_rggb8", "bayer_bggr8",
    "bayer_gbrg8",  "bayer_grbg8",  "bayer_rggb16", "bayer_bggr16", "bayer_gbrg16", "bayer_grbg16"};

bool IsBayer(const std::string& encoding) { return encoding.rfind("bayer_", 0) == 0; }

struct Photo {
  const char* file;
  const char* dictionary;
  std::vector<int> ids;  // test/data/README.md: what the photos' own test suites assert
};

const Photo kPhotos[] = {
    {"opencv_tutorial/singlemarkersoriginal.jpg", "DICT_6X6_250", {23, 40, 62, 98, 124, 203}},
    {"ubiquity_fiducials/tag_245-246_d7_14cm.png", "DICT_5X5_1000", {245, 246}},
};

std::vector<ArucoTag> DetectIn(const DetectorImage& input, const std::string& dictionary) {
  PreprocessOptions options;
  options.format = input.format;
  cv::Mat grey;
  PreprocessFrame(input.pixels, grey, options);
  DetectorConfig config;
  config.dictionary = dictionary;
  std::vector<ArucoTag> tags = Detect(grey, Detector(config));
  std::sort(tags.begin(), tags.end(), [](const ArucoTag& a, const ArucoTag& b) { return a.id < b.id; });
  return tags;
}

std::vector<int> Ids(const std::vector<ArucoTag>& tags) {
  std::vector<int> ids;
  for (const auto& tag : tags) ids.push_back(tag.id);
  return ids;
}

// The same ids as bgr8 and each corner within `tolerance` px of bgr8's; returns the largest offset.
double ExpectSameAsBgr8(const std::vector<ArucoTag>& tags, const std::vector<ArucoTag>& reference,
                        double tolerance, const std::string& what) {
  EXPECT_EQ(Ids(tags), Ids(reference)) << what;
  double worst = 0.0;
  if (Ids(tags) != Ids(reference)) return worst;
  for (size_t i = 0; i < tags.size(); ++i) {
    for (int c = 0; c < 4; ++c) {
      worst = std::max(worst, cv::norm(cv::Point2d(tags[i].corners[c]) - cv::Point2d(reference[i].corners[c])));
    }
  }
  EXPECT_LE(worst, tolerance) << what;
  return worst;
}

class EveryEncoding : public ::testing::TestWithParam<std::string> {};

TEST_P(EveryEncoding, RealPhotosGiveBgr8sMarkers) {
  const std::string encoding = GetParam();
  const double tolerance = IsBayer(encoding) ? 1.0 : 0.5;
  for (const auto& photo : kPhotos) {
    const cv::Mat bgr = LoadBgr(photo.file);
    const auto reference = DetectIn(DetectorImageFrom(Encode(bgr, "bgr8")), photo.dictionary);
    ASSERT_EQ(Ids(reference), photo.ids) << photo.file;

    const sensor_msgs::ImagePtr message = Encode(bgr, encoding);
    const DetectorImage input = DetectorImageFrom(message);
    ASSERT_EQ(input.pixels.size(), bgr.size());
    const double worst = ExpectSameAsBgr8(DetectIn(input, photo.dictionary), reference, tolerance,
                                          encoding + " " + photo.file);
    RecordProperty(std::string(photo.file).substr(0, 10) + "_max_corner_offset_px", std::to_string(worst));
    std::printf("%-13s %-45s largest corner offset from bgr8 %.3f px\n", encoding.c_str(), photo.file, worst);
  }
}

// Encodings PreprocessFrame reads as they are must not be copied: the view is the message's buffer.
TEST_P(EveryEncoding, SharesTheBufferWhenThePixelsNeedNoConversion) {
  const std::string encoding = GetParam();
  const auto message = Encode(cv::Mat(6, 8, CV_8UC3, cv::Scalar(10, 20, 30)), encoding);
  const DetectorImage input = DetectorImageFrom(message);
  const std::vector<std::string> as_sent = {"bgr8", "8UC3", "rgb8", "bgra8", "8UC4", "rgba8", "mono8", "8UC1", "mono16", "16UC1"};
  const bool in_place = std::count(as_sent.begin(), as_sent.end(), encoding) == 1;
  EXPECT_EQ(input.pixels.data == message->data.data(), in_place) << encoding;
  EXPECT_EQ(static_cast<bool>(input.shared), in_place) << encoding;
  EXPECT_EQ(input.pixels.size(), cv::Size(8, 6)) << encoding;
}

INSTANTIATE_TEST_SUITE_P(ImageInput, EveryEncoding, ::testing::ValuesIn(kAllEncodings),
                         [](const ::testing::TestParamInfo<std::string>& info) { return info.param; });

// Solid red, green, blue and white quadrants: a Bayer pattern read with the wrong phase, swapped
// chroma bytes or swapped red and blue all move the colours far from these.
cv::Mat ColourQuadrants() {
  cv::Mat bgr(64, 64, CV_8UC3);
  bgr(cv::Rect(0, 0, 32, 32)).setTo(cv::Scalar(0, 0, 255));
  bgr(cv::Rect(32, 0, 32, 32)).setTo(cv::Scalar(0, 255, 0));
  bgr(cv::Rect(0, 32, 32, 32)).setTo(cv::Scalar(255, 0, 0));
  bgr(cv::Rect(32, 32, 32, 32)).setTo(cv::Scalar(255, 255, 255));
  return bgr;
}

// The quadrants' insides, 3 px from every edge, where demosaicing and chroma sharing see one colour.
cv::Mat Insides() {
  cv::Mat mask(64, 64, CV_8UC1, cv::Scalar(0));
  for (int x : {0, 32}) {
    for (int y : {0, 32}) mask(cv::Rect(x + 3, y + 3, 26, 26)).setTo(255);
  }
  return mask;
}

double LargestDifference(const cv::Mat& a, const cv::Mat& b, const cv::Mat& mask) {
  cv::Mat difference;
  cv::absdiff(a, b, difference);
  std::vector<cv::Mat> channels;
  cv::split(difference, channels);
  double worst = 0.0;
  for (const auto& channel : channels) {
    double largest = 0.0;
    cv::minMaxLoc(channel, nullptr, &largest, nullptr, nullptr, mask);
    worst = std::max(worst, largest);
  }
  return worst;
}

TEST_P(EveryEncoding, KeepsColoursAndTheirGrey) {
  const std::string encoding = GetParam();
  const cv::Mat bgr = ColourQuadrants();
  const auto message = Encode(bgr, encoding);
  const bool mono = encoding.find("mono") == 0 || encoding == "8UC1" || encoding == "16UC1";
  const bool yuv = encoding.find("yuv") == 0;

  // The detector's grey: BGR2GRAY's weights whatever the encoding; yuv keeps the sensor's luma range.
  cv::Mat grey = Convert(bgr, cv::COLOR_BGR2GRAY);
  if (yuv) grey.convertTo(grey, CV_8U, 219.0 / 255.0, 16.0);
  DetectorImage input = DetectorImageFrom(message);
  PreprocessOptions options;
  options.format = input.format;
  cv::Mat detector_grey;
  PreprocessFrame(input.pixels, detector_grey, options);
  EXPECT_LE(LargestDifference(detector_grey, grey, Insides()), 2.0) << encoding;

  const cv::Mat overlay = OverlayBgr8(message);
  ASSERT_EQ(overlay.type(), CV_8UC3) << encoding;
  const cv::Mat expected = mono ? Convert(Convert(bgr, cv::COLOR_BGR2GRAY), cv::COLOR_GRAY2BGR) : bgr;
  EXPECT_LE(LargestDifference(overlay, expected, Insides()), yuv ? 3.0 : 1.0) << encoding;
}

// Refusals are arucotag::Error whose message holds `needle` (the encoding, and what is wrong);
// anything else escaping fails the test as an uncaught exception.
template <typename Call>
void ExpectRefused(Call call, const std::vector<std::string>& needles, const std::string& what) {
  try {
    call();
    ADD_FAILURE() << what << ": accepted";
  } catch (const Error& e) {
    for (const auto& needle : needles) {
      EXPECT_NE(std::string(e.what()).find(needle), std::string::npos) << what << ": " << e.what();
    }
  }
}

void ExpectBothRefuse(const sensor_msgs::ImagePtr& message, const std::vector<std::string>& needles,
                      const std::string& what) {
  ExpectRefused([&] { DetectorImageFrom(message); }, needles, what + " (detector)");
  ExpectRefused([&] { OverlayBgr8(message); }, needles, what + " (overlay)");
}

TEST_P(EveryEncoding, RefusesMalformedMessagesByName) {
  const std::string encoding = GetParam();
  const auto valid = [&] { return Encode(cv::Mat(6, 8, CV_8UC3, cv::Scalar(10, 20, 30)), encoding); };
  const uint32_t row = valid()->step - kRowPadding;

  auto message = valid();
  message->width = 0;
  ExpectBothRefuse(message, {encoding, "empty"}, "zero width");
  message = valid();
  message->height = 0;
  ExpectBothRefuse(message, {encoding, "empty"}, "zero height");
  message = valid();
  message->step = row - 1;
  ExpectBothRefuse(message, {encoding, "shorter than a row"}, "step short of a row");
  message = valid();
  message->data.resize(message->data.size() - 1);
  ExpectBothRefuse(message, {encoding, "bytes"}, "data one byte short");
  message = valid();
  message->data.clear();
  ExpectBothRefuse(message, {encoding, "bytes"}, "no data");
  // A few bytes claiming gigapixels: refused from the arithmetic, before anything is allocated.
  for (uint32_t side : {65536u, 0x7fffffffu, 0xffffffffu}) {
    message = valid();
    message->width = message->height = side;
    message->step = 0xffffffffu;
    message->data.resize(16);
    ExpectBothRefuse(message, {encoding}, "claims " + std::to_string(side) + " px a side");
  }

  const bool wide = encoding.find("16") != std::string::npos;
  message = valid();
  message->is_bigendian = 1;
  if (wide) {
    ExpectBothRefuse(message, {encoding, "big-endian"}, "big-endian");
    message = valid();
    message->step = row + 1;
    ExpectBothRefuse(message, {encoding, "whole number"}, "step splits a sample");
  } else {
    EXPECT_NO_THROW(DetectorImageFrom(message)) << encoding << ": byte order means nothing for 8-bit samples";
  }
  if (encoding.find("yuv") == 0) {
    message = Message(cv::Mat(4, 7, CV_8UC2, cv::Scalar(128, 60)), encoding);
    ExpectBothRefuse(message, {encoding, "odd width"}, "odd width");
  }
}

// Images too small to demosaic or pair up are converted or refused by name, never a crash.
TEST_P(EveryEncoding, TinyImagesAreConvertedOrRefused) {
  const std::string encoding = GetParam();
  for (const cv::Size size : {cv::Size(2, 1), cv::Size(2, 2), cv::Size(4, 3), cv::Size(2, 5), cv::Size(1, 1)}) {
    const auto message = Encode(cv::Mat(size, CV_8UC3, cv::Scalar(10, 200, 30)), encoding);
    const std::string what = encoding + " " + std::to_string(size.width) + "x" + std::to_string(size.height);
    try {
      EXPECT_EQ(DetectorImageFrom(message).pixels.size(), size) << what;
      EXPECT_EQ(OverlayBgr8(message).size(), size) << what;
    } catch (const Error& e) {
      EXPECT_NE(std::string(e.what()).find(encoding), std::string::npos) << what << ": " << e.what();
    }
  }
}

TEST(ImageInput, UnknownEncodingsNameThemselves) {
  for (const std::string encoding : {"hsv8", "32FC1", "16SC1", "bayer_rggb12", "", "BGR8"}) {
    auto message = Message(cv::Mat(4, 4, CV_8UC3, cv::Scalar::all(7)), "bgr8");
    message->encoding = encoding;
    ExpectBothRefuse(message, {"'" + encoding + "'", "unsupported", "bgr8, "}, "encoding '" + encoding + "'");
  }
  ExpectRefused([] { DetectorImageFrom(sensor_msgs::ImageConstPtr()); }, {"no image"}, "null message");
}

sensor_msgs::CompressedImage Compressed(const cv::Mat& pixels, const std::string& extension,
                                        const std::string& format) {
  sensor_msgs::CompressedImage compressed;
  compressed.format = format;
  EXPECT_TRUE(cv::imencode(extension, pixels, compressed.data)) << format;
  return compressed;
}

// compressed_image_transport's jpeg (lossy, default quality) and png, and what each decodes to.
TEST(ImageInput, CompressedPhotosGiveBgr8sMarkers) {
  for (const auto& photo : kPhotos) {
    const cv::Mat bgr = LoadBgr(photo.file);
    const auto reference = DetectIn(DetectorImageFrom(Encode(bgr, "bgr8")), photo.dictionary);
    ASSERT_EQ(Ids(reference), photo.ids) << photo.file;
    const cv::Mat grey = Convert(bgr, cv::COLOR_BGR2GRAY);
    struct Case {
      sensor_msgs::CompressedImage compressed;
      std::string decoded_encoding;
      double tolerance;
    };
    const Case cases[] = {
        {Compressed(bgr, ".jpg", "bgr8; jpeg compressed bgr8"), "bgr8", 0.5},
        {Compressed(bgr, ".png", "bgr8; png compressed bgr8"), "bgr8", 0.5},
        {Compressed(Convert(bgr, cv::COLOR_BGR2RGB), ".png", "rgb8; png compressed bgr8"), "bgr8", -1.0},
        {Compressed(grey, ".jpg", "mono8; jpeg compressed mono8"), "mono8", 0.5},
        {Compressed(grey, ".png", "mono8; png compressed mono8"), "mono8", 0.5},
        {Compressed(To16(grey), ".png", "mono16; png compressed mono16"), "mono16", 0.5},
        {Compressed(To16(bgr), ".png", "bgr16; png compressed bgr16"), "bgr16", 0.5},
        // A mosaic compresses as grey; the format string keeps what it was.
        {Compressed(Mosaic(bgr, "rggb"), ".png", "bayer_rggb8; png compressed "), "bayer_rggb8", 1.0},
        {Compressed(To16(Mosaic(bgr, "gbrg")), ".png", "bayer_gbrg16; png compressed "), "bayer_gbrg16", 1.0},
    };
    for (const auto& test : cases) {
      const std::string what = test.compressed.format + " " + photo.file;
      const sensor_msgs::ImagePtr decoded = DecodeCompressedImage(test.compressed);
      EXPECT_EQ(decoded->encoding, test.decoded_encoding) << what;
      EXPECT_EQ(cv::Size(decoded->width, decoded->height), bgr.size()) << what;
      const auto tags = DetectIn(DetectorImageFrom(test.compressed), photo.dictionary);
      if (test.tolerance < 0) {
        // The file holds rgb as if it were bgr (the publisher's bug to make): ids still agree.
        EXPECT_EQ(Ids(tags), Ids(reference)) << what;
        continue;
      }
      const double worst = ExpectSameAsBgr8(tags, reference, test.tolerance, what);
      std::printf("%-32s %-45s largest corner offset from bgr8 %.3f px\n", test.compressed.format.c_str(),
                  photo.file, worst);
    }
  }
}

TEST(ImageInput, CompressedDecodesKeepTheHeader) {
  auto compressed = Compressed(ColourQuadrants(), ".png", "bgr8; png compressed bgr8");
  compressed.header.frame_id = "camera_optical";
  compressed.header.seq = 42;
  compressed.header.stamp = ros::Time(12, 34);
  const auto decoded = DecodeCompressedImage(compressed);
  EXPECT_EQ(decoded->header.frame_id, "camera_optical");
  EXPECT_EQ(decoded->header.stamp, ros::Time(12, 34));
  EXPECT_EQ(OverlayBgr8(decoded).at<cv::Vec3b>(5, 40), cv::Vec3b(0, 255, 0));
}

void PutBigEndian(std::vector<uint8_t>& data, size_t at, uint32_t value, int bytes) {
  for (int i = bytes - 1; i >= 0; --i, value >>= 8) data[at + i] = static_cast<uint8_t>(value & 0xff);
}

TEST(ImageInput, RefusesMalformedCompressedImagesByFormat) {
  const cv::Mat bgr = ColourQuadrants();
  const auto png = Compressed(bgr, ".png", "png");
  const auto jpeg = Compressed(bgr, ".jpg", "jpeg");
  const auto refuse = [](const sensor_msgs::CompressedImage& compressed, const std::vector<std::string>& needles,
                         const std::string& what, size_t max_pixels = kMaxCompressedPixels) {
    ExpectRefused([&] { DecodeCompressedImage(compressed, max_pixels); }, needles, what);
  };

  auto bad = png;
  bad.data.clear();
  refuse(bad, {"'png'", "empty"}, "no data");
  bad.data.assign(100, 0x42);
  refuse(bad, {"'png'", "neither jpeg nor png"}, "garbage");
  bad = Compressed(bgr, ".bmp", "bmp");
  refuse(bad, {"'bmp'", "neither jpeg nor png"}, "a bmp");
  bad = png;
  bad.data.resize(60);
  refuse(bad, {"'png'", "cannot decode"}, "png cut after its header");
  bad = png;
  bad.data.resize(20);
  refuse(bad, {"'png'", "cut short"}, "png cut inside its header");
  bad = jpeg;
  bad.data.resize(300);
  refuse(bad, {"'jpeg'"}, "jpeg cut short");

  // Headers claiming huge images are refused before OpenCV would allocate them.
  bad = png;
  PutBigEndian(bad.data, 16, 100000, 4);
  PutBigEndian(bad.data, 20, 100000, 4);
  refuse(bad, {"'png'", "100000x100000"}, "png claiming 10 Gpx");
  bad = jpeg;
  const uint8_t start_of_frame[] = {0xff, 0xc0};
  const auto sof = std::search(bad.data.begin(), bad.data.end(), std::begin(start_of_frame), std::end(start_of_frame));
  ASSERT_NE(sof, bad.data.end());
  const size_t at = sof - bad.data.begin() + 2;  // length, precision, height, width
  PutBigEndian(bad.data, at + 3, 65535, 2);
  PutBigEndian(bad.data, at + 5, 65535, 2);
  refuse(bad, {"'jpeg'", "65535x65535"}, "jpeg claiming 4 Gpx");
  PutBigEndian(bad.data, at + 3, 0, 2);
  refuse(bad, {"'jpeg'", "x0"}, "jpeg with its height left to a later marker");
  refuse(png, {"'png'", "64x64"}, "png above a lower limit", 64 * 64 - 1);
  EXPECT_NO_THROW(DecodeCompressedImage(png, 64 * 64));
}

// Every prefix of a real file, the way a dropped connection cuts one: decoded (libjpeg pads a cut
// scan with grey) or refused by format, never a crash or an image of another size.
TEST(ImageInput, CutCompressedFilesAreDecodedOrRefused) {
  for (const std::string extension : {".png", ".jpg"}) {
    const auto whole = Compressed(ColourQuadrants(), extension, extension.substr(1));
    int decoded = 0, refused = 0;
    for (size_t length = 0; length < whole.data.size(); ++length) {
      auto cut = whole;
      cut.data.resize(length);
      try {
        const auto image = DecodeCompressedImage(cut);
        EXPECT_EQ(cv::Size(image->width, image->height), cv::Size(64, 64)) << extension << " cut at " << length;
        ++decoded;
      } catch (const Error& e) {
        EXPECT_NE(std::string(e.what()).find("'" + extension.substr(1) + "'"), std::string::npos) << e.what();
        ++refused;
      }
    }
    // Without the file's first few hundred bytes (headers and tables) nothing decodes.
    EXPECT_GT(refused, 100) << extension;
    std::printf("%s: %d prefixes decoded, %d refused\n", extension.c_str(), decoded, refused);
  }
}

}  // namespace
}  // namespace arucotag

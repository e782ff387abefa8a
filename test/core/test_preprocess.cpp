// PreprocessFrame: every supported input becomes the same grey image; the input is never touched.
#include <gtest/gtest.h>
#include <opencv2/imgproc.hpp>

#include "scene.hpp"

namespace arucotag {
namespace {

cv::Mat Scene() {
  const sim::Camera camera = test::RoverCamera();
  return sim::RenderScene(camera, {sim::FacingCamera(2, 0.15, {0.1, 0.0, 1.5}, 20.0)}, sim::RenderOptions());
}

TEST(Preprocess, AllEncodingsGiveTheSameGreyAndTheSameDetection) {
  const cv::Mat bgr = Scene();
  cv::Mat reference;
  PreprocessFrame(bgr, reference);
  ASSERT_EQ(reference.type(), CV_8UC1);
  const auto expected = Detect(reference, Detector());
  ASSERT_EQ(expected.size(), 1u);

  cv::Mat rgb, bgra, rgba, mono16;
  cv::cvtColor(bgr, rgb, cv::COLOR_BGR2RGB);
  cv::cvtColor(bgr, bgra, cv::COLOR_BGR2BGRA);
  cv::cvtColor(bgr, rgba, cv::COLOR_BGR2RGBA);
  // A 12-bit sensor: values up to 4095 must still fill the 8-bit range, so mono16 comes out
  // stretched by 255 / its maximum.
  reference.convertTo(mono16, CV_16U, 16.0);
  double reference_max = 0;
  cv::minMaxLoc(reference, nullptr, &reference_max);
  cv::Mat stretched;
  reference.convertTo(stretched, CV_8U, 255.0 / reference_max);
  const std::vector<std::pair<cv::Mat, PixelFormat>> inputs = {
      {rgb, PixelFormat::kRgb8}, {bgra, PixelFormat::kBgra8}, {rgba, PixelFormat::kRgba8},
      {reference, PixelFormat::kMono8}, {mono16, PixelFormat::kMono16}, {bgra, PixelFormat::kAuto}};
  for (const auto& [input, format] : inputs) {
    PreprocessOptions options;
    options.format = format;
    cv::Mat grey;
    PreprocessFrame(input, grey, options);
    ASSERT_EQ(grey.type(), CV_8UC1);
    double max_diff = 0;
    const cv::Mat& expected_grey = format == PixelFormat::kMono16 ? stretched : reference;
    cv::minMaxLoc(cv::abs(grey - expected_grey), nullptr, &max_diff);
    EXPECT_LE(max_diff, 1.0) << static_cast<int>(format);
    const auto tags = Detect(grey, Detector());
    ASSERT_EQ(tags.size(), 1u);
    EXPECT_EQ(tags[0].id, 2);
    EXPECT_LE(cv::norm(tags[0].corners[0] - expected[0].corners[0]), 0.05);
  }
}

TEST(Preprocess, NeverWritesItsInput) {
  const cv::Mat bgr = Scene();
  const cv::Mat copy = bgr.clone();
  PreprocessOptions options;
  options.equalize = true;
  options.unsharp_amount = 1.0;
  cv::Mat out;
  PreprocessFrame(bgr, out, options);
  EXPECT_EQ(cv::norm(bgr, copy, cv::NORM_INF), 0.0);

  // Even when asked to write over it.
  cv::Mat grey;
  PreprocessFrame(bgr, grey);
  const cv::Mat grey_copy = grey.clone();
  cv::Mat alias = grey;
  PreprocessFrame(grey, alias, options);
  EXPECT_EQ(cv::norm(grey, grey_copy, cv::NORM_INF), 0.0);
  EXPECT_GT(cv::norm(alias, grey_copy, cv::NORM_INF), 0.0);
}

TEST(Preprocess, UnsharpMaskIsARealSharpenNotAThreshold) {
  // A soft ramp stays a ramp (many grey levels), unlike the origin's 9 x identity kernel.
  cv::Mat ramp(20, 256, CV_8UC1);
  for (int u = 0; u < 256; ++u) ramp.col(u).setTo(u);
  cv::GaussianBlur(ramp, ramp, cv::Size(), 3.0);
  PreprocessOptions options;
  options.unsharp_amount = 1.0;
  cv::Mat out;
  PreprocessFrame(ramp, out, options);
  std::set<int> levels(out.begin<uchar>(), out.end<uchar>());
  EXPECT_GT(levels.size(), 200u);
  EXPECT_NEAR(out.at<uchar>(10, 128), ramp.at<uchar>(10, 128), 2);
}

}  // namespace
}  // namespace arucotag

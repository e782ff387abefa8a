// libFuzzer harness: the core on arbitrary frames. The first bytes choose the frame's size and
// OpenCV type, the preprocessing and detector options; the rest are its pixels (repeated to fill
// the frame). PreprocessFrame, Detect (again on the tracking path when it found markers) and
// DrawDetections must return or throw arucotag::Error, nothing else.
#include <cstddef>
#include <cstdint>
#include <vector>

#include <arucotag/detector.hpp>
#include <arucotag/draw.hpp>
#include <arucotag/preprocess.hpp>

#include "fuzz_input.hpp"

namespace {

using arucotag::fuzz::FuzzInput;

// Every type a camera or a caller might hand over, supported or not.
const int kTypes[] = {CV_8UC1, CV_8UC3, CV_8UC4, CV_16UC1, CV_8UC2, CV_16UC3, CV_16UC4,
                      CV_8SC1, CV_16SC1, CV_32FC1, CV_32FC3, CV_64FC1, CV_32SC1};
const arucotag::PixelFormat kFormats[] = {
    arucotag::PixelFormat::kAuto,  arucotag::PixelFormat::kBgr8,  arucotag::PixelFormat::kRgb8,
    arucotag::PixelFormat::kBgra8, arucotag::PixelFormat::kRgba8, arucotag::PixelFormat::kMono8,
    arucotag::PixelFormat::kMono16};
const arucotag::CornerRefinement kRefinements[] = {
    arucotag::CornerRefinement::kNone, arucotag::CornerRefinement::kSubpix, arucotag::CornerRefinement::kContour,
    arucotag::CornerRefinement::kApriltag, arucotag::CornerRefinement::kEdge};

template <class T, std::size_t N>
const T& Pick(FuzzInput& in, const T (&table)[N]) {
  return table[in.Byte() % N];
}

}  // namespace

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  FuzzInput in(data, size);
  // Up to 320x240: big enough for every detector path (pyramid levels, tracking strips), small
  // enough for tens of executions a second under the sanitizers.
  const int rows = in.Int(0, 240), cols = in.Int(0, 320);
  const int type = Pick(in, kTypes);

  arucotag::PreprocessOptions preprocess;
  preprocess.format = Pick(in, kFormats);
  const std::uint8_t flags = in.Byte();
  preprocess.equalize = flags & 1;
  preprocess.clahe_clip_limit = in.Double(2.0);
  preprocess.clahe_tile_grid = in.Int(-2, 64);
  preprocess.unsharp_amount = (flags & 2) ? in.Double(1.0) : 0.0;
  preprocess.unsharp_sigma = in.Double(1.5);

  arucotag::DetectorConfig config;
  const auto& names = arucotag::DictionaryNames();
  config.dictionary = names[in.Byte() % names.size()];
  config.corner_refinement = Pick(in, kRefinements);
  config.fast_path = !(flags & 4);
  config.tracking = !(flags & 8);
  config.detect_inverted_marker = flags & 16;
  config.marker_border_bits = 1 + ((flags >> 5) & 1);
  config.pattern_fit_max_side = (flags & 64) ? 256 : 56;
  config.pattern_fit_max_markers = (flags & 128) ? 0 : 8;

  // Tags with arbitrary corners (NaN, inf, far outside the frame) for the overlay alone.
  std::vector<arucotag::ArucoTag> extra(in.Int(0, 3));
  for (auto& tag : extra) {
    tag.id = in.Int(-1, 1000);
    for (auto& corner : tag.corners) corner = cv::Point2f(in.Double(cols), in.Double(rows));
    tag.distance = in.Double(2.0);
  }

  cv::Mat frame(rows, cols, type);
  const std::vector<std::uint8_t> pixels = in.Rest();
  const std::size_t bytes = frame.total() * frame.elemSize();
  auto* dst = frame.ptr<std::uint8_t>();
  for (std::size_t i = 0; i < bytes; ++i) dst[i] = pixels.empty() ? 0 : pixels[i % pixels.size()];

  cv::Mat grey;
  try {
    arucotag::PreprocessFrame(frame, grey, preprocess);
  } catch (const arucotag::Error&) {
    grey = frame;  // Detect must refuse what PreprocessFrame refused, without crashing
  }
  try {
    const arucotag::Detector detector(config);
    std::vector<arucotag::ArucoTag> tags = arucotag::Detect(grey, detector);
    if (config.fast_path && config.tracking && !tags.empty()) tags = arucotag::Detect(grey, detector);
    tags.insert(tags.end(), extra.begin(), extra.end());
    cv::Mat overlay = grey.clone();
    arucotag::DrawDetections(overlay, tags);
  } catch (const arucotag::Error&) {
  }
  try {
    cv::Mat overlay = frame.clone();
    arucotag::DrawDetections(overlay, extra);
  } catch (const arucotag::Error&) {
  }
  return 0;
}

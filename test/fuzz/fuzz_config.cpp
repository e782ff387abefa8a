// libFuzzer harness: configuration parsing. The first byte picks what the rest is:
// - names: the dictionary, corner refinement and encoding parsers (a name they accept must
//   round-trip);
// - a dynamic_reconfigure/Config message from the wire, handled as the nodelet's reconfigure
//   server does (__fromMessage__, __clamp__, ApplyReconfigure, then a Detector built from it);
// - a DetectorConfig and PreprocessOptions with arbitrary values.
// Whatever Detector's validation accepts must then detect a real marker frame without crashing,
// hanging or exhausting memory; what it refuses, it refuses with arucotag::Error.
#include <arucotag/ros/parameters.hpp>

#include <cstddef>
#include <cstdint>
#include <cstdlib>

#include <opencv2/aruco.hpp>
#include <opencv2/imgproc.hpp>
#include <ros/console.h>

#include "bounded_message.hpp"
#include "fuzz_input.hpp"

namespace {

using arucotag::fuzz::FuzzInput;

// A 160x120 frame holding DICT_4X4_50 marker 7, 60 px wide, slightly rotated.
const cv::Mat& Frame() {
  static const cv::Mat frame = [] {
    cv::Mat marker;
    cv::aruco::drawMarker(cv::aruco::getPredefinedDictionary(cv::aruco::DICT_4X4_50), 7, 60, marker);
    cv::Mat frame(120, 160, CV_8UC1, cv::Scalar(255));
    marker.copyTo(frame(cv::Rect(50, 30, 60, 60)));
    const cv::Mat turn = cv::getRotationMatrix2D(cv::Point2f(80, 60), 7.0, 1.0);
    cv::warpAffine(frame, frame, turn, frame.size(), cv::INTER_LINEAR, cv::BORDER_CONSTANT, cv::Scalar(255));
    return frame;
  }();
  return frame;
}

void Check(bool ok) {
  if (!ok) std::abort();  // a finding: libFuzzer saves the input
}

void Names(FuzzInput& in) {
  const std::string name = in.String(40);
  try {
    Check(arucotag::DictionaryNames()[arucotag::DictionaryFromName(name)] == name);
  } catch (const arucotag::Error&) {
  }
  try {
    Check(arucotag::CornerRefinementName(arucotag::CornerRefinementFromName(name)) == name);
  } catch (const arucotag::Error&) {
  }
  try {
    (void)arucotag::PixelFormatFromEncoding(name);
  } catch (const arucotag::Error&) {
  }
}

// Detection with a configuration that validation let through, and preprocessing with options.
void Run(const arucotag::DetectorConfig& config, const arucotag::PreprocessOptions& preprocess) {
  try {
    cv::Mat grey;
    arucotag::PreprocessFrame(Frame(), grey, preprocess);
  } catch (const arucotag::Error&) {
  }
  try {
    const arucotag::Detector detector(config);
    (void)arucotag::Detect(Frame(), detector);
    (void)arucotag::Detect(Frame(), detector);  // the tracking path
  } catch (const arucotag::Error&) {
  }
}

void Reconfigure(const std::uint8_t* data, std::size_t size) {
  dynamic_reconfigure::Config message;
  if (!arucotag::fuzz::Deserialize(data, size, message)) return;
  arucotag::DetectorConfig detector;
  arucotag::PreprocessOptions preprocess;
  arucotag::ArucotagDetectorConfig config = arucotag::ToReconfigure(detector, preprocess);
  config.__fromMessage__(message);
  config.__clamp__();
  try {
    arucotag::ApplyReconfigure(config, detector, preprocess);
  } catch (const arucotag::Error&) {
    return;
  }
  Run(detector, preprocess);
}

void Values(FuzzInput& in) {
  arucotag::DetectorConfig c;
  const auto& names = arucotag::DictionaryNames();
  c.dictionary = names[in.Byte() % names.size()];
  c.corner_refinement = static_cast<arucotag::CornerRefinement>(in.Int(0, 4));
  const auto integer = [&in](int& value) {
    if (in.Bool()) value = in.Bool() ? in.Int(-3, 300) : in.Raw<int>();
  };
  const auto real = [&in](double& value) {
    if (in.Bool()) value = in.Double(value == 0.0 ? 1.0 : value);
  };
  for (int* value : {&c.adaptive_thresh_win_size_min, &c.adaptive_thresh_win_size_max,
                     &c.adaptive_thresh_win_size_step, &c.min_distance_to_border, &c.marker_border_bits,
                     &c.perspective_remove_pixel_per_cell, &c.corner_refinement_win_size,
                     &c.corner_refinement_max_iterations, &c.full_search_interval, &c.pattern_fit_max_side,
                     &c.pattern_fit_sharp_max_side, &c.pattern_fit_max_markers}) {
    integer(*value);
  }
  for (double* value : {&c.adaptive_thresh_constant, &c.min_marker_perimeter_rate, &c.max_marker_perimeter_rate,
                        &c.polygonal_approx_accuracy_rate, &c.min_corner_distance_rate, &c.min_marker_distance_rate,
                        &c.perspective_remove_ignored_margin_per_cell, &c.max_erroneous_bits_in_border_rate,
                        &c.min_otsu_std_dev, &c.error_correction_rate, &c.corner_refinement_min_accuracy,
                        &c.default_side_length}) {
    real(*value);
  }
  const std::uint8_t flags = in.Byte();
  c.detect_inverted_marker = flags & 1;
  c.fast_path = flags & 2;
  c.tracking = flags & 4;
  for (int i = in.Int(0, 3); i > 0; --i) c.allowed_ids.push_back(in.Int(-2, 60));
  for (int i = in.Int(0, 3); i > 0; --i) c.ignored_ids.push_back(in.Int(-2, 60));
  for (int i = in.Int(0, 3); i > 0; --i) c.side_lengths[in.Int(-2, 60)] = in.Double(0.15);

  arucotag::PreprocessOptions p;
  p.equalize = flags & 8;
  real(p.clahe_clip_limit);
  integer(p.clahe_tile_grid);
  real(p.unsharp_amount);
  real(p.unsharp_sigma);
  Run(c, p);
}

}  // namespace

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  // __fromMessage__ logs unknown names with ROS_ERROR: keep the fuzzer's output readable.
  static const bool quiet = ros::console::set_logger_level(ROSCONSOLE_DEFAULT_NAME, ros::console::levels::Fatal);
  (void)quiet;
  if (size < 1) return 0;
  FuzzInput in(data + 1, size - 1);
  switch (data[0] % 3) {
    case 0:
      Names(in);
      break;
    case 1:
      Reconfigure(data + 1, size - 1);
      break;
    default:
      Values(in);
      break;
  }
  return 0;
}

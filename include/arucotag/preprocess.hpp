#pragma once

#include <opencv2/core.hpp>

namespace arucotag {

/// Pixel layout of an input frame. cv::Mat does not carry channel order, so say it when it matters.
enum class PixelFormat { kAuto, kBgr8, kRgb8, kBgra8, kRgba8, kMono8, kMono16 };

/// Parses a ROS/cv_bridge encoding name ("bgr8", "rgb8", "bgra8", "rgba8", "mono8", "mono16",
/// "8UC1", "8UC3", "16UC1"); throws arucotag::Error naming the supported ones otherwise.
PixelFormat PixelFormatFromEncoding(const std::string& encoding);

/// Optional image steps before detection. All off by default: only switch one on for footage where
/// it was measured to help (README, "Preprocessing").
struct PreprocessOptions {
  PixelFormat format = PixelFormat::kAuto;  ///< kAuto: 1 channel 8/16-bit = mono, 3 = BGR, 4 = BGRA
  /// Contrast-limited adaptive histogram equalisation: lifts markers in shade or glare.
  bool equalize = false;
  double clahe_clip_limit = 2.0;  ///< CLAHE contrast limit
  int clahe_tile_grid = 8;        ///< CLAHE tiles per image side, 1 to 256
  /// Unsharp mask: out = in + amount * (in - gaussian(in, sigma)). 0 disables.
  double unsharp_amount = 0.0;
  double unsharp_sigma = 1.5;  ///< px, at most 100
};

/// Converts any supported frame to the 8-bit single-channel image the detector wants, then applies
/// the enabled optional steps. Never modifies `in`; `out` may not alias `in` when a step is enabled
/// (it is reallocated). 16-bit mono is scaled by its own maximum so 10/12-bit sensors use the full
/// 8-bit range. Throws arucotag::Error on an empty image, an unsupported depth or channel count, or
/// a format that does not match the channel count.
void PreprocessFrame(const cv::Mat& in, cv::Mat& out, const PreprocessOptions& options = {});

}  // namespace arucotag

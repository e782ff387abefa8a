#include <arucotag/preprocess.hpp>

#include <string>

#include <opencv2/imgproc.hpp>

#include <arucotag/aruco_tag.hpp>

namespace arucotag {

PixelFormat PixelFormatFromEncoding(const std::string& encoding) {
  if (encoding == "bgr8" || encoding == "8UC3") return PixelFormat::kBgr8;
  if (encoding == "rgb8") return PixelFormat::kRgb8;
  if (encoding == "bgra8" || encoding == "8UC4") return PixelFormat::kBgra8;
  if (encoding == "rgba8") return PixelFormat::kRgba8;
  if (encoding == "mono8" || encoding == "8UC1") return PixelFormat::kMono8;
  if (encoding == "mono16" || encoding == "16UC1") return PixelFormat::kMono16;
  throw Error("unsupported image encoding '" + encoding +
              "' (supported: bgr8, rgb8, bgra8, rgba8, mono8, mono16, 8UC1, 8UC3, 8UC4, 16UC1)");
}

namespace {

constexpr int kMaxTileGrid = 256;
constexpr double kMaxUnsharpSigma = 100.0;

PixelFormat ResolveFormat(const cv::Mat& in, PixelFormat format) {
  const int channels = in.channels();
  const int depth = in.depth();
  if (format == PixelFormat::kAuto) {
    if (channels == 1) return depth == CV_16U ? PixelFormat::kMono16 : PixelFormat::kMono8;
    if (channels == 3) return PixelFormat::kBgr8;
    if (channels == 4) return PixelFormat::kBgra8;
    throw Error("PreprocessFrame: unsupported channel count " + std::to_string(channels));
  }
  const bool matches = (format == PixelFormat::kMono8 && channels == 1 && depth == CV_8U) ||
                       (format == PixelFormat::kMono16 && channels == 1 && depth == CV_16U) ||
                       ((format == PixelFormat::kBgr8 || format == PixelFormat::kRgb8) && channels == 3 &&
                        depth == CV_8U) ||
                       ((format == PixelFormat::kBgra8 || format == PixelFormat::kRgba8) && channels == 4 &&
                        depth == CV_8U);
  if (!matches) {
    throw Error("PreprocessFrame: image with " + std::to_string(channels) + " channel(s) of depth " +
                std::to_string(depth) + " does not match the declared pixel format");
  }
  return format;
}

}  // namespace

void PreprocessFrame(const cv::Mat& in, cv::Mat& out, const PreprocessOptions& options) {
  if (in.empty()) {
    throw Error("PreprocessFrame: empty image");
  }
  if (in.depth() != CV_8U && in.depth() != CV_16U) {
    throw Error("PreprocessFrame: unsupported depth (want 8-bit, or 16-bit mono)");
  }
  if (in.depth() == CV_16U && in.channels() != 1) {
    throw Error("PreprocessFrame: 16-bit images must be single-channel mono16");
  }
  // Work into a fresh buffer so `in` is never written, even when the caller passes it as `out`.
  cv::Mat grey;
  switch (ResolveFormat(in, options.format)) {
    case PixelFormat::kBgr8:
      cv::cvtColor(in, grey, cv::COLOR_BGR2GRAY);
      break;
    case PixelFormat::kRgb8:
      cv::cvtColor(in, grey, cv::COLOR_RGB2GRAY);
      break;
    case PixelFormat::kBgra8:
      cv::cvtColor(in, grey, cv::COLOR_BGRA2GRAY);
      break;
    case PixelFormat::kRgba8:
      cv::cvtColor(in, grey, cv::COLOR_RGBA2GRAY);
      break;
    case PixelFormat::kMono16: {
      double max_value = 0.0;
      cv::minMaxLoc(in, nullptr, &max_value);
      in.convertTo(grey, CV_8U, max_value > 0.0 ? 255.0 / max_value : 1.0);
      break;
    }
    case PixelFormat::kMono8:
    case PixelFormat::kAuto:
      grey = in.clone();
      break;
  }
  // Bounds fuzz_config found: OpenCV allocates tile_grid^2 tiles (a grid of 10^9 asked for exabytes) and
  // refuses a Gaussian kernel of a huge sigma with cv::Exception.
  if (options.equalize) {
    if (!(options.clahe_clip_limit > 0.0) || options.clahe_tile_grid < 1 || options.clahe_tile_grid > kMaxTileGrid) {
      throw Error("PreprocessFrame: clahe_clip_limit must be > 0 and clahe_tile_grid 1 to " +
                  std::to_string(kMaxTileGrid));
    }
    cv::createCLAHE(options.clahe_clip_limit, cv::Size(options.clahe_tile_grid, options.clahe_tile_grid))
        ->apply(grey, grey);
  }
  if (options.unsharp_amount > 0.0) {
    if (!(options.unsharp_sigma > 0.0 && options.unsharp_sigma <= kMaxUnsharpSigma)) {
      throw Error("PreprocessFrame: unsharp_sigma must be > 0 and at most " + std::to_string(kMaxUnsharpSigma) + " px");
    }
    cv::Mat blurred;
    cv::GaussianBlur(grey, blurred, cv::Size(), options.unsharp_sigma);
    cv::addWeighted(grey, 1.0 + options.unsharp_amount, blurred, -options.unsharp_amount, 0.0, grey);
  }
  out = grey;
}

}  // namespace arucotag

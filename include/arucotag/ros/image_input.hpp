#pragma once

// Image messages as the detector takes them. Every encoding cv_bridge knows (and yuv422_yuy2, which
// Debian's does not) becomes an image PreprocessFrame accepts, sharing the message's buffer where
// the layout allows. Messages are untrusted: each is validated before anything reads or allocates
// from its declared size. Nothing here logs; errors are arucotag::Error naming the encoding.
#include <cstddef>
#include <string>

#include <cv_bridge/cv_bridge.h>
#include <opencv2/core.hpp>
#include <sensor_msgs/CompressedImage.h>
#include <sensor_msgs/Image.h>

#include <arucotag/preprocess.hpp>

namespace arucotag {

/// An image ready for PreprocessFrame: 8- or 16-bit mono, or 8-bit bgr/rgb/bgra/rgba.
struct DetectorImage {
  cv::Mat pixels;      ///< read-only when `shared` is set: it is the message's buffer
  PixelFormat format;  ///< pass as PreprocessOptions::format
  /// Set when `pixels` views the message (keeps it alive); null when `pixels` is a converted copy.
  cv_bridge::CvImageConstPtr shared;
};

/// The encodings DetectorImageFrom and OverlayBgr8 accept, comma-separated, for messages and docs.
const std::string& SupportedImageEncodings();

/// The image the detector reads from `image`. mono8/mono16/8UC1/16UC1/bgr8/rgb8/bgra8/rgba8/8UC3/
/// 8UC4 are shared with cv_bridge::toCvShare; yuv422 (UYVY) and yuv422_yuy2 give their luma as mono8
/// (the sensor's own grey, no colour round trip); bayer_*8 and bayer_*16 are demosaiced straight to
/// mono8 and mono16; bgr16/rgb16/bgra16/rgba16 become mono16. Throws arucotag::Error naming the
/// encoding on an unknown or unsupported one, an empty image, a step shorter than a row or not a
/// whole number of samples, data shorter than height * step, big-endian 16-bit data, or an odd
/// width for packed 4:2:2.
DetectorImage DetectorImageFrom(const sensor_msgs::ImageConstPtr& image);

/// A bgr8 copy of `image` to draw the overlay on: colour as the camera saw it (bayer is demosaiced
/// in colour), mono replicated, 16-bit scaled by its own maximum like PreprocessFrame so 10- and
/// 12-bit sensors are not drawn black. Same validation and errors as DetectorImageFrom.
cv::Mat OverlayBgr8(const sensor_msgs::ImageConstPtr& image);

/// Largest image DecodeCompressedImage decodes by default: 64 Mpx, 8 times a 4K frame.
constexpr std::size_t kMaxCompressedPixels = std::size_t{1} << 26;

/// Decodes a jpeg or png CompressedImage (what compressed_image_transport publishes) with
/// cv_bridge into an Image with the same header: mono8, mono16, bgr8, bgra8, bgr16 or bgra16 as the
/// file holds. The size in the file's header is read and checked against `max_pixels` before
/// decoding, so a few bytes claiming a huge image never allocate it. Throws arucotag::Error naming
/// the message's format on empty or undecodable data, another file type, or a larger image.
sensor_msgs::ImagePtr DecodeCompressedImage(const sensor_msgs::CompressedImage& compressed,
                                            std::size_t max_pixels = kMaxCompressedPixels);

/// DetectorImageFrom(DecodeCompressedImage(compressed)): for callers that need no Image message.
DetectorImage DetectorImageFrom(const sensor_msgs::CompressedImage& compressed);

}  // namespace arucotag

// Borders of a binary image for the candidate search (internal to arucotag_core). See contours.cpp.
#pragma once

#include <cstdint>
#include <vector>

#include <opencv2/core.hpp>

namespace arucotag::internal {

/// Pixel values of the image BorderScan reads: background and foreground. It marks followed border
/// pixels with values of its own, in place.
constexpr uchar kBackground = 0;
constexpr uchar kForeground = 1;

/// Every border (outer and hole) of a CV_8UC1 image of kBackground/kForeground pixels whose
/// outermost rows and columns are background, with the points of cv::findContours(RETR_LIST,
/// CHAIN_APPROX_NONE, offset (-1, -1)): coordinates are those of the image without its frame. That
/// function lists the same borders, last found first.
class BorderScan {
 public:
  /// Each border's points are written to the front of `buffer`, in turn: it grows to the longest
  /// border and is not shrunk, so its size is not the border's (size() is).
  BorderScan(cv::Mat& binary, std::vector<cv::Point>& buffer);

  /// The next border in raster order: false when there is none left. Its points, every pixel of it
  /// (CHAIN_APPROX_NONE), are points()[0, size()) until the next call.
  bool Next();
  const cv::Point* points() const { return buffer_.data(); }
  int size() const { return size_; }
  /// Next(), with the border's points copied into `points`.
  bool Next(std::vector<cv::Point>& points);
  /// Whether the border Next gave last is a hole's (foreground round background).
  bool hole() const { return hole_; }

 private:
  uchar* data_;
  size_t step_;
  int rows_, cols_;
  int x_ = 1, y_ = 1;
  bool hole_ = false;
  std::vector<cv::Point>& buffer_;
  int size_ = 0;
};

/// A closed polygon's bounding box and twice its signed area (the shoelace sum), exactly: what
/// cv::boundingRect gives, and twice what cv::contourArea(points, true) gives, in one pass.
struct Outline {
  cv::Rect box;
  int64_t twice_area = 0;
};
Outline Measure(const std::vector<cv::Point>& points);

/// cv::approxPolyDP(points, polygon, epsilon, true) as OpenCV 4 computes it up to 4.12 (Douglas-Peucker
/// from two points far apart, by distance to the chord's line, then vertices on almost straight
/// runs dropped; opencv/opencv#28119 later measures to the segment), in integer arithmetic where
/// OpenCV's is exact anyway: the same vertices at a fraction of the cost, on any OpenCV version.
/// `points` is a border BorderScan gives (a closed chain of unit steps): its length bounds how far
/// apart two points lie, which is what lets chains under 2^15 points use 32-bit distances. Points
/// spread wider than half their count along an axis can overflow them.
void ApproximatePolygon(const std::vector<cv::Point>& points, double epsilon, std::vector<cv::Point>& polygon);

}  // namespace arucotag::internal

#include <arucotag/draw.hpp>

#include <cstdio>
#include <string>

#include <opencv2/imgproc.hpp>

namespace arucotag {

void DrawDetections(cv::Mat& image, const std::vector<ArucoTag>& tags) {
  if (image.empty()) {
    throw Error("DrawDetections: empty image");
  }
  if (image.depth() != CV_8U || (image.channels() != 1 && image.channels() != 3)) {
    throw Error("DrawDetections: want an 8-bit image with 1 or 3 channels (got " +
                std::to_string(image.channels()) + " channel(s) of OpenCV depth " +
                std::to_string(image.depth()) + ")");
  }
  const bool grey = image.channels() == 1;
  const cv::Scalar outline = grey ? cv::Scalar(255) : cv::Scalar(0, 255, 0);
  const cv::Scalar first_corner = grey ? cv::Scalar(0) : cv::Scalar(0, 0, 255);
  const cv::Scalar text = grey ? cv::Scalar(255) : cv::Scalar(255, 255, 0);
  // Scale strokes with the image so overlays stay legible from VGA to 4K.
  const int thickness = std::max(1, std::min(image.cols, image.rows) / 360);
  const double font_scale = 0.4 * thickness + 0.1;

  for (const auto& tag : tags) {
    std::vector<cv::Point> quad;
    for (const auto& c : tag.corners) quad.emplace_back(cvRound(c.x), cvRound(c.y));
    cv::polylines(image, quad, true, outline, thickness, cv::LINE_AA);
    const int half = 2 + thickness;
    cv::rectangle(image, quad[0] - cv::Point(half, half), quad[0] + cv::Point(half, half), first_corner, cv::FILLED);

    std::string label = "id " + std::to_string(tag.id);
    if (tag.HasPose() && std::isfinite(tag.distance)) {
      char buffer[32];
      std::snprintf(buffer, sizeof(buffer), " %.2fm", tag.distance);
      label += buffer;
    }
    // Above the tag, centred on it: inside it the label hid the bits, and neighbouring faces of a
    // post overlapped their labels.
    const cv::Point2f centre = FindTagCenter(tag);
    const cv::Rect box = cv::boundingRect(quad);
    int baseline = 0;
    const cv::Size size = cv::getTextSize(label, cv::FONT_HERSHEY_SIMPLEX, font_scale, thickness, &baseline);
    const int above = box.y - 2 * thickness - baseline;
    const cv::Point origin(cvRound(centre.x) - size.width / 2,
                           above - size.height >= 0 ? above : box.y + box.height + size.height + 2 * thickness);
    // A dark halo keeps the label readable on the marker's black and white cells.
    cv::putText(image, label, origin, cv::FONT_HERSHEY_SIMPLEX, font_scale, cv::Scalar::all(0), thickness + 2,
                cv::LINE_AA);
    cv::putText(image, label, origin, cv::FONT_HERSHEY_SIMPLEX, font_scale, text, thickness, cv::LINE_AA);
  }
}

}  // namespace arucotag

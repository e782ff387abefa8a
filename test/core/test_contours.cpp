// BorderScan, the candidate search's border follower, against what it replaces:
// cv::findContours(RETR_LIST, CHAIN_APPROX_NONE) through OpenCV's C API, which keeps each border's
// bounding box and lists the borders in its own order. Same borders, same order, same points, same
// boxes, on thresholded real photos, on noise of every density, and on shapes made to be awkward:
// isolated pixels, one-pixel lines and rings, diagonal touches, holes inside holes, the frame's edge.
#include <algorithm>
#include <string>
#include <vector>

#include <gtest/gtest.h>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>
#include <opencv2/imgproc/imgproc_c.h>

#include "contours.hpp"

namespace arucotag::internal {
namespace {

struct Border {
  std::vector<cv::Point> points;
  cv::Rect box;
};

// OpenCV's borders of a 0/1 image with a zero frame, in the order it lists them.
std::vector<Border> OpenCvBorders(cv::Mat binary) {
  cv::MemStorage storage(cvCreateMemStorage(0));
  CvMat header = cvMat(binary);
  CvSeq* first = nullptr;
  cvFindContours(&header, storage, &first, sizeof(CvContour), CV_RETR_LIST, CV_CHAIN_APPROX_NONE, cvPoint(-1, -1));
  std::vector<Border> borders;
  for (CvSeq* seq = first; seq; seq = seq->h_next) {
    Border b;
    b.points.resize(seq->total);
    cvCvtSeqToArray(seq, b.points.data(), CV_WHOLE_SEQ);
    b.box = reinterpret_cast<CvContour*>(seq)->rect;
    borders.push_back(b);
  }
  return borders;
}

// BorderScan's, last found first as OpenCV lists them.
std::vector<Border> ScanBorders(cv::Mat binary) {
  std::vector<Border> borders;
  std::vector<cv::Point> buffer;
  BorderScan scan(binary, buffer);
  Border b;
  while (scan.Next(b.points)) {
    b.box = cv::boundingRect(b.points);
    borders.push_back(b);
  }
  std::reverse(borders.begin(), borders.end());
  return borders;
}

// `inside` (0/nonzero) as the 0/1 image with a zero frame the candidate search hands over.
cv::Mat Framed(const cv::Mat& inside) {
  cv::Mat binary;
  cv::copyMakeBorder(inside != 0, binary, 1, 1, 1, 1, cv::BORDER_CONSTANT, cv::Scalar(0));
  return binary / 255;
}

// With `compared`, the number of borders compared is added to it.
void ExpectSameBorders(const cv::Mat& binary, const std::string& what, size_t* compared = nullptr) {
  const std::vector<Border> expected = OpenCvBorders(binary.clone());
  const std::vector<Border> got = ScanBorders(binary.clone());
  ASSERT_EQ(got.size(), expected.size()) << what;
  if (compared) *compared += got.size();
  for (size_t i = 0; i < got.size(); ++i) {
    ASSERT_EQ(got[i].box, expected[i].box) << what << ", border " << i;
    ASSERT_EQ(got[i].points, expected[i].points) << what << ", border " << i;
    // Measure: OpenCV's box and area of the same points, in one pass.
    const Outline outline = Measure(got[i].points);
    ASSERT_EQ(outline.box, expected[i].box) << what << ", border " << i;
    ASSERT_EQ(0.5 * static_cast<double>(outline.twice_area), cv::contourArea(got[i].points, true))
        << what << ", border " << i;
  }
}

TEST(BorderScan, SameBordersAsOpenCvOnThresholdedPhotos) {
  size_t borders = 0;
  for (const char* name : {"opencv_tutorial/singlemarkersoriginal.jpg", "opencv_tutorial/choriginal.jpg",
                           "ubiquity_fiducials/tag_245-246_d7_14cm.png"}) {
    const cv::Mat grey = cv::imread(std::string(ARUCOTAG_TEST_DATA) + "/" + name, cv::IMREAD_GRAYSCALE);
    ASSERT_FALSE(grey.empty()) << name;
    for (int window : {3, 7, 23}) {
      cv::Mat inside;
      cv::adaptiveThreshold(grey, inside, 1, cv::ADAPTIVE_THRESH_MEAN_C, cv::THRESH_BINARY_INV, window, 7);
      ExpectSameBorders(Framed(inside), std::string(name) + " window " + std::to_string(window), &borders);
    }
  }
  EXPECT_GT(borders, 1000u);  // the photos' clutter, not a handful of shapes
}

// ApproximatePolygon against cv::approxPolyDP (closed) on every border of the thresholded photos, at
// the tolerances the candidate search uses (a share of the border's length) and fixed ones. OpenCV
// after 4.12 measures to the chord's segment, not its line (opencv/opencv#28119): nothing to compare.
TEST(ApproximatePolygon, SameVerticesAsOpenCvOnPhotoBorders) {
  if (CV_VERSION_MAJOR * 100 + CV_VERSION_MINOR > 412) GTEST_SKIP() << "cv::approxPolyDP's distance changed";
  int compared = 0, quads = 0;
  std::vector<cv::Point> ours, theirs;
  for (const char* name : {"opencv_tutorial/singlemarkersoriginal.jpg", "opencv_tutorial/chocclusion_original.jpg",
                           "ubiquity_fiducials/tag_01_d7_14cm.png"}) {
    const cv::Mat grey = cv::imread(std::string(ARUCOTAG_TEST_DATA) + "/" + name, cv::IMREAD_GRAYSCALE);
    ASSERT_FALSE(grey.empty()) << name;
    cv::Mat inside;
    cv::adaptiveThreshold(grey, inside, 1, cv::ADAPTIVE_THRESH_MEAN_C, cv::THRESH_BINARY_INV, 7, 7);
    for (const Border& border : ScanBorders(Framed(inside))) {
      const double n = static_cast<double>(border.points.size());
      for (const double epsilon : {0.03 * n, 0.05 * n, 1.0, 3.0}) {
        ApproximatePolygon(border.points, epsilon, ours);
        cv::approxPolyDP(border.points, theirs, epsilon, true);
        ASSERT_EQ(ours, theirs) << name << ", " << border.points.size() << " points, epsilon " << epsilon;
        ++compared;
        quads += ours.size() == 4;
      }
    }
  }
  EXPECT_GT(compared, 10000);
  EXPECT_GT(quads, 100);  // markers and clutter squares among them, not only specks
}

// Borders of 2^15 points or more take ApproximatePolygon's 64-bit distances: a closed polygon of that
// many points around a large wobbly quad (a 9000 x 8000 px frame's worth), against cv::approxPolyDP.
TEST(ApproximatePolygon, SameVerticesAsOpenCvOnALongBorder) {
  if (CV_VERSION_MAJOR * 100 + CV_VERSION_MINOR > 412) GTEST_SKIP() << "cv::approxPolyDP's distance changed";
  const std::vector<cv::Point> corners = {{10, 20}, {9010, 300}, {8700, 8020}, {150, 7900}};
  std::vector<cv::Point> chain;
  for (size_t c = 0; c < corners.size(); ++c) {
    cv::LineIterator line(corners[c], corners[(c + 1) % corners.size()], 8);
    for (int i = 0; i + 1 < line.count; ++i, ++line) {
      cv::Point p = line.pos();
      p.y += (i / 500) % 2;  // a step every 500 points, so the sides are not straight
      chain.push_back(p);
    }
  }
  ASSERT_GE(chain.size(), size_t{1} << 15);
  std::vector<cv::Point> ours, theirs;
  for (const double epsilon : {0.5, 2.0, 0.03 * chain.size()}) {
    ApproximatePolygon(chain, epsilon, ours);
    cv::approxPolyDP(chain, theirs, epsilon, true);
    EXPECT_EQ(ours, theirs) << "epsilon " << epsilon;
  }
  EXPECT_EQ(ours.size(), 4u);  // at the coarse tolerance, the quad
}

// Widths from 1 to 71 px: rows end within each block size of the scan (16 pixels, 8, then 1).
TEST(BorderScan, SameBordersAsOpenCvOnNoise) {
  cv::RNG rng(14);
  for (int trial = 0; trial < 60; ++trial) {
    const cv::Size size(1 + rng.uniform(0, 70), 1 + rng.uniform(0, 50));
    const double density = rng.uniform(0.02, 0.98);
    cv::Mat values(size, CV_32F);
    rng.fill(values, cv::RNG::UNIFORM, 0.0, 1.0);
    cv::Mat inside = values < density;
    if (trial % 3 == 0) cv::dilate(inside, inside, cv::Mat());  // blobs with holes, not only specks
    ExpectSameBorders(Framed(inside), "noise " + std::to_string(trial));
  }
}

TEST(BorderScan, SameBordersAsOpenCvOnAwkwardShapes) {
  cv::Mat inside(40, 61, CV_8U, cv::Scalar(0));
  inside.at<uchar>(0, 0) = 1;                                                  // isolated, at the frame
  inside.at<uchar>(5, 5) = 1;                                                  // isolated
  inside.at<uchar>(6, 6) = 1;                                                  // diagonal neighbour
  cv::line(inside, {10, 2}, {30, 2}, cv::Scalar(1));                           // one-pixel line
  cv::line(inside, {2, 10}, {20, 30}, cv::Scalar(1));                          // diagonal line
  cv::rectangle(inside, cv::Rect(25, 8, 20, 20), cv::Scalar(1));               // one-pixel ring
  cv::rectangle(inside, cv::Rect(29, 12, 12, 12), cv::Scalar(1), cv::FILLED);  // ... holding a block
  inside(cv::Rect(32, 15, 6, 6)).setTo(0);                                     // ... with a hole
  inside.at<uchar>(17, 34) = 1;                                                // ... holding a pixel
  cv::circle(inside, {52, 30}, 8, cv::Scalar(1), 2);                           // ring to the edge
  inside.col(60).setTo(1);                                                     // the right edge
  inside.row(39).setTo(1);                                                     // the bottom edge
  ExpectSameBorders(Framed(inside), "shapes");
  ExpectSameBorders(Framed(cv::Mat(5, 7, CV_8U, cv::Scalar(1))), "all foreground");
  ExpectSameBorders(Framed(cv::Mat(5, 7, CV_8U, cv::Scalar(0))), "all background");
}

}  // namespace
}  // namespace arucotag::internal

// The overlay's label layout: labels stay inside the image, never overlap each other, keep off the
// tags, and a moved label is tied to its tag by a leader line that DrawDetections draws.
// With ARUCOTAG_DRAW_OUT=<dir> the drawn frames are written there as PNGs to look at.
#include <algorithm>
#include <cstdlib>
#include <map>
#include <string>

#include <gtest/gtest.h>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>

#include "scene.hpp"

namespace arucotag {
namespace {

const std::vector<cv::Size> kSizes = {{640, 480}, {1280, 720}, {1920, 1080}};

std::string SizeName(cv::Size size) { return std::to_string(size.width) + "x" + std::to_string(size.height); }

/// A tag at the marker's true projected corners, with a PnP-like pose so its label shows the distance.
ArucoTag TagOf(const sim::Camera& camera, const sim::Marker& marker) {
  ArucoTag tag;
  tag.id = marker.id;
  tag.corners = sim::ProjectCorners(camera, marker);
  tag.pose_source = PoseSource::kPnp;
  tag.tvec = marker.tvec;
  tag.distance = cv::norm(marker.tvec);
  return tag;
}

std::vector<ArucoTag> TagsOf(const sim::Camera& camera, const std::vector<sim::Marker>& markers) {
  std::vector<ArucoTag> tags;
  for (const auto& m : markers) tags.push_back(TagOf(camera, m));
  return tags;
}

/// Two faces of a square post 0.2 m wide, seen edge-on (each face turned 45 degrees), `range` m away.
std::vector<sim::Marker> PostFaces(double range, int left_id, int right_id) {
  const double h = 0.1 / std::sqrt(2.0);
  return {sim::FacingCamera(left_id, 0.15, {-h, 0.0, range + h}, -45.0),
          sim::FacingCamera(right_id, 0.15, {h, 0.0, range + h}, 45.0)};
}

/// 5 x 3 markers of 0.1 m on a 0.16 m pitch, 2 m away: the labels are wider than the gaps.
std::vector<sim::Marker> Crowd() {
  std::vector<sim::Marker> markers;
  for (int row = 0; row < 3; ++row) {
    for (int col = 0; col < 5; ++col) {
      markers.push_back(sim::FacingCamera(10 * row + col, 0.1, {0.16 * (col - 2), 0.16 * (row - 1), 2.0}, 0.0, 0.0,
                                          7.0 * (col - row)));
    }
  }
  return markers;
}

double CoveredArea(const cv::Rect& box, const ArucoTag& tag) {
  const std::vector<cv::Point2f> rect = {cv::Point2f(box.x, box.y), cv::Point2f(box.x + box.width, box.y),
                                         cv::Point2f(box.x + box.width, box.y + box.height),
                                         cv::Point2f(box.x, box.y + box.height)};
  std::vector<cv::Point2f> hull, inter;
  cv::convexHull(std::vector<cv::Point2f>(tag.corners.begin(), tag.corners.end()), hull);
  return cv::intersectConvexConvex(rect, hull, inter, true);
}

/// Checks what every layout must hold; returns how many labels were moved (and have a leader).
int CheckLayout(cv::Size size, const std::vector<ArucoTag>& tags, const std::vector<LabelPlacement>& labels,
                bool tags_must_stay_clear, const std::string& what) {
  SCOPED_TRACE(what + " at " + SizeName(size));
  EXPECT_EQ(labels.size(), tags.size());
  const cv::Rect image(cv::Point(), size);
  int moved = 0;
  for (size_t i = 0; i < labels.size(); ++i) {
    const LabelPlacement& label = labels[i];
    SCOPED_TRACE("label " + label.text);
    const std::string id = "id " + std::to_string(tags[i].id);
    EXPECT_TRUE(label.text == id || label.text.rfind(id + " ", 0) == 0) << "for tag " << tags[i].id;
    EXPECT_FALSE(label.box.empty());
    EXPECT_EQ(label.box & image, label.box) << "box " << label.box << " leaves the image";
    EXPECT_TRUE(label.box.contains(label.text_origin));
    for (size_t j = 0; j < i; ++j) {
      EXPECT_TRUE((label.box & labels[j].box).empty()) << label.box << " overlaps " << labels[j].text << " "
                                                       << labels[j].box;
    }
    if (tags_must_stay_clear) {
      for (const auto& tag : tags) EXPECT_EQ(CoveredArea(label.box, tag), 0.0) << "covers tag " << tag.id;
    }
    if (label.moved) {
      ++moved;
      // The leader starts on the tag's own outline and ends on the label's border.
      std::vector<cv::Point2f> quad(tags[i].corners.begin(), tags[i].corners.end());
      EXPECT_LT(std::abs(cv::pointPolygonTest(quad, label.anchor, true)), 0.01) << label.anchor;
      const cv::Point end(cvRound(label.leader_end.x), cvRound(label.leader_end.y));
      EXPECT_TRUE(label.box.contains(end)) << end;
      const bool on_border = end.x == label.box.x || end.x == label.box.br().x - 1 || end.y == label.box.y ||
                             end.y == label.box.br().y - 1;
      EXPECT_TRUE(on_border) << end << " inside " << label.box;
    } else {
      // Unmoved labels sit centred on their tag (unless the image edge pushed them), just above or below it.
      const cv::Point2f centre = FindTagCenter(tags[i]);
      const cv::Rect bounds = cv::boundingRect(std::vector<cv::Point2f>(tags[i].corners.begin(), tags[i].corners.end()));
      const bool pushed = label.box.x == 0 || label.box.br().x == size.width;
      if (!pushed) {
        EXPECT_NEAR(label.box.x + 0.5 * label.box.width, centre.x, 1.0);
      }
      const bool above = label.box.br().y <= bounds.y && label.box.br().y >= bounds.y - 20;
      const bool below = label.box.y >= bounds.br().y && label.box.y <= bounds.br().y + 20;
      EXPECT_TRUE(above || below) << label.box << " tag " << bounds;
    }
  }
  return moved;
}

/// Draws the tags onto a flat grey frame and checks that the label boxes and leaders DrawDetections
/// drew are the ones LayoutLabels returned; returns how many leaders it saw.
int CheckDrawn(cv::Size size, const std::vector<ArucoTag>& tags, const std::vector<LabelPlacement>& labels) {
  cv::Mat image(size, CV_8UC3, cv::Scalar::all(128));
  DrawDetections(image, tags);
  int leaders = 0;
  for (const auto& label : labels) {
    SCOPED_TRACE(label.text + " at " + SizeName(size));
    // Just inside the box's frame the padding is the dimmed background (128 / 4); the inner corner
    // furthest from the leader, whose end dims with the box.
    const cv::Rect inner(label.box.x + 1, label.box.y + 1, label.box.width - 2, label.box.height - 2);
    cv::Point far = inner.tl();
    for (const cv::Point p : {inner.tl(), cv::Point(inner.br().x - 1, inner.y), inner.br() - cv::Point(1, 1),
                              cv::Point(inner.x, inner.br().y - 1)}) {
      if (cv::norm(cv::Point2f(p) - label.leader_end) > cv::norm(cv::Point2f(far) - label.leader_end)) far = p;
    }
    EXPECT_EQ(image.at<cv::Vec3b>(far), cv::Vec3b(32, 32, 32)) << far;
    // The frame is in the text colour (cyan).
    EXPECT_EQ(image.at<cv::Vec3b>(label.box.y, label.box.x + label.box.width / 2), cv::Vec3b(255, 255, 0));
    const cv::Point2f mid = (label.anchor + label.leader_end) * 0.5f;
    // Labels are drawn over leaders: where a crowd leaves no other way, a leader runs under a label.
    const bool under_a_label = std::any_of(labels.begin(), labels.end(), [&](const LabelPlacement& other) {
      return (other.box + cv::Size(2, 2) - cv::Point(1, 1)).contains(cv::Point(cvRound(mid.x), cvRound(mid.y)));
    });
    if (label.moved && cv::norm(label.anchor - label.leader_end) > 6.0 && !under_a_label) {
      ++leaders;
      // The brightest pixel next to the leader's midpoint: a one-pixel anti-aliased line may fall between.
      cv::Vec3b pixel;
      for (int dy = -1; dy <= 1; ++dy) {
        for (int dx = -1; dx <= 1; ++dx) {
          const cv::Vec3b p = image.at<cv::Vec3b>(cvRound(mid.y) + dy, cvRound(mid.x) + dx);
          if (p[0] > pixel[0]) pixel = p;
        }
      }
      EXPECT_GT(pixel[0], 150) << "leader line at " << mid;
      EXPECT_LT(pixel[2], 100) << "leader line at " << mid;
    }
  }
  return leaders;
}

void MaybeWrite(const cv::Mat& image, const std::string& name) {
  if (const char* dir = std::getenv("ARUCOTAG_DRAW_OUT")) cv::imwrite(std::string(dir) + "/" + name + ".png", image);
}

/// Renders the markers, draws the tags at their true corners and writes the frame when asked to.
void RenderAndWrite(const sim::Camera& camera, const std::vector<sim::Marker>& markers,
                    const std::vector<ArucoTag>& tags, const std::string& name) {
  if (!std::getenv("ARUCOTAG_DRAW_OUT")) return;
  sim::RenderOptions options;
  options.supersample = 2;
  cv::Mat image = sim::RenderScene(camera, markers, options);
  DrawDetections(image, tags);
  MaybeWrite(image, name + "_" + SizeName(camera.size));
}

TEST(Draw, FacesOfOnePostGetSeparateLabels) {
  for (const cv::Size size : kSizes) {
    const sim::Camera camera = sim::MakeCamera(size, 65.0);
    for (const auto& [range, right_id] : std::vector<std::pair<double, int>>{{3.0, 7}, {1.5, 8}, {6.0, 7}}) {
      const auto markers = PostFaces(range, 7, right_id);
      const auto tags = TagsOf(camera, markers);
      const auto labels = LayoutLabels(size, tags);
      const std::string what = "post at " + std::to_string(range) + " m";
      ASSERT_EQ(labels.size(), 2u);
      // Both centred above their faces (the old layout) the labels would collide.
      const auto default_box = [&](size_t i) {
        const cv::Point2f c = FindTagCenter(tags[i]);
        return cv::Rect(cvRound(c.x - labels[i].box.width / 2.0), 0, labels[i].box.width, labels[i].box.height);
      };
      ASSERT_FALSE((default_box(0) & default_box(1)).empty()) << what;
      EXPECT_GE(CheckLayout(size, tags, labels, true, what), 1);
      CheckDrawn(size, tags, labels);
      RenderAndWrite(camera, markers, tags, "post_" + std::to_string(int(range * 10)) + "dm");
    }
  }
}

TEST(Draw, CrowdedTagsKeepLabelsApartAndOffTheTags) {
  const auto markers = Crowd();
  for (const cv::Size size : kSizes) {
    const sim::Camera camera = sim::MakeCamera(size, 65.0);
    const auto tags = TagsOf(camera, markers);
    const auto labels = LayoutLabels(size, tags);
    EXPECT_GE(CheckLayout(size, tags, labels, true, "crowd"), 5);
    EXPECT_GE(CheckDrawn(size, tags, labels), 5);
    RenderAndWrite(camera, markers, tags, "crowd");
  }
}

TEST(Draw, TagsAtTheBorderKeepTheirLabelsInside) {
  for (const cv::Size size : kSizes) {
    const int w = size.width, h = size.height, s = size.height / 8;
    std::vector<ArucoTag> tags;
    const std::vector<cv::Point> corners = {{0, 0}, {w - s, 0}, {w - s, h - s}, {0, h - s}, {w / 2, 0}, {w / 2, h - s}};
    for (size_t i = 0; i < corners.size(); ++i) {
      ArucoTag tag;
      tag.id = 100 + int(i);
      const cv::Point2f o(corners[i]);
      tag.corners = {{o, o + cv::Point2f(s - 1, 0), o + cv::Point2f(s - 1, s - 1), o + cv::Point2f(0, s - 1)}};
      tags.push_back(tag);
    }
    const auto labels = LayoutLabels(size, tags);
    CheckLayout(size, tags, labels, true, "border");
    CheckDrawn(size, tags, labels);
    cv::Mat image(size, CV_8UC3, cv::Scalar::all(128));
    DrawDetections(image, tags);
    MaybeWrite(image, "border_" + SizeName(size));
  }
}

TEST(Draw, TextGrowsWithTheImageAndStaysLegible) {
  ArucoTag tag;
  tag.id = 42;
  tag.corners = {{{100, 100}, {140, 100}, {140, 140}, {100, 140}}};
  std::map<int, cv::Size> box;
  for (const cv::Size size : {cv::Size(320, 240), cv::Size(640, 480), cv::Size(1920, 1080), cv::Size(3840, 2160)}) {
    const auto labels = LayoutLabels(size, {tag});
    ASSERT_EQ(labels.size(), 1u);
    EXPECT_EQ(labels[0].text, "id 42");
    box[size.height] = labels[0].box.size();
  }
  // Hershey digits under about 9 px stop being readable: the smallest frame keeps that floor.
  EXPECT_GE(box[240].height, 13);
  EXPECT_GE(box[480].height, 15);
  // From VGA up the text scales with the frame, so it reads the same on a screen.
  EXPECT_NEAR(double(box[1080].height) / box[480].height, 1080.0 / 480.0, 0.4);
  EXPECT_NEAR(double(box[2160].height) / box[480].height, 2160.0 / 480.0, 0.8);
}

TEST(Draw, RealPhotoLabelsDoNotOverlap) {
  DetectorConfig config;
  config.dictionary = "DICT_6X6_250";
  const std::string path = std::string(ARUCOTAG_TEST_DATA) + "/opencv_tutorial/singlemarkersoriginal.jpg";
  cv::Mat photo = cv::imread(path, cv::IMREAD_COLOR);
  ASSERT_FALSE(photo.empty());
  const auto tags = Detect(test::LoadGrey("opencv_tutorial/singlemarkersoriginal.jpg"), Detector(config));
  ASSERT_EQ(tags.size(), 6u);
  const auto labels = LayoutLabels(photo.size(), tags);
  CheckLayout(photo.size(), tags, labels, true, "singlemarkersoriginal");
  DrawDetections(photo, tags);
  MaybeWrite(photo, "singlemarkers_" + SizeName(photo.size()));
  // The same photo as a 1080p frame.
  cv::Mat big;
  cv::resize(cv::imread(path, cv::IMREAD_COLOR), big, {1440, 1080}, 0, 0, cv::INTER_CUBIC);
  std::vector<ArucoTag> scaled = tags;
  for (auto& tag : scaled) {
    for (auto& c : tag.corners) c = (c + cv::Point2f(0.5f, 0.5f)) * 2.25f - cv::Point2f(0.5f, 0.5f);
  }
  CheckLayout(big.size(), scaled, LayoutLabels(big.size(), scaled), true, "singlemarkersoriginal x2.25");
  DrawDetections(big, scaled);
  MaybeWrite(big, "singlemarkers_" + SizeName(big.size()));
}

TEST(Draw, MoreLabelsThanRoomStayInsideTheImage) {
  // 150 tags on a 320x240 frame: their labels alone cover more than the frame, so no layout keeps
  // them apart, but every box stays in the frame.
  const cv::Size size(320, 240);
  std::vector<ArucoTag> tags;
  for (int i = 0; i < 150; ++i) {
    ArucoTag tag;
    tag.id = i;
    const cv::Point2f o(float(i % 15) * 21.0f, float(i / 15) * 24.0f);
    tag.corners = {{o, o + cv::Point2f(10, 0), o + cv::Point2f(10, 10), o + cv::Point2f(0, 10)}};
    tags.push_back(tag);
  }
  const auto labels = LayoutLabels(size, tags);
  ASSERT_EQ(labels.size(), tags.size());
  for (const auto& label : labels) EXPECT_EQ(label.box & cv::Rect(cv::Point(), size), label.box) << label.text;
  cv::Mat image(size, CV_8UC1, cv::Scalar(128));
  EXPECT_NO_THROW(DrawDetections(image, tags));
}

TEST(Draw, FrameNarrowerThanALabelClipsIt) {
  ArucoTag tag;
  tag.id = 123456;
  tag.corners = {{{10, 10}, {20, 10}, {20, 20}, {10, 20}}};
  const cv::Size size(40, 30);
  const auto labels = LayoutLabels(size, {tag});
  ASSERT_EQ(labels.size(), 1u);
  EXPECT_FALSE(labels[0].box.empty());
  EXPECT_EQ(labels[0].box & cv::Rect(cv::Point(), size), labels[0].box);
  cv::Mat image(size, CV_8UC3, cv::Scalar::all(128));
  EXPECT_NO_THROW(DrawDetections(image, {tag}));
}

TEST(Draw, LayoutRejectsAnEmptySize) { EXPECT_THROW(LayoutLabels({0, 480}, {}), Error); }

}  // namespace
}  // namespace arucotag

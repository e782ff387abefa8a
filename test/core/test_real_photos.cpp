// Real third-party photos with the answers their own test suites assert (test/data/README.md).
#include <algorithm>
#include <map>
#include <set>
#include <string>

#include <gtest/gtest.h>
#include <opencv2/imgcodecs.hpp>

#include <arucotag/arucotag.hpp>

#include "scene.hpp"

namespace arucotag {
namespace {

using Quad = std::array<cv::Point2f, 4>;

std::vector<ArucoTag> DetectIn(const std::string& relative, const std::string& dictionary, CornerRefinement refine) {
  DetectorConfig config;
  config.dictionary = dictionary;
  config.corner_refinement = refine;
  return Detect(test::LoadGrey(relative), Detector(config));
}

std::multiset<int> Ids(const std::vector<ArucoTag>& tags) {
  std::multiset<int> ids;
  for (const auto& t : tags) ids.insert(t.id);
  return ids;
}

// OpenCV asserts each coordinate separately (|dx| <= 1 and |dy| <= 1).
double MaxAxisError(const ArucoTag& tag, const Quad& expected) {
  double worst = 0.0;
  for (int i = 0; i < 4; ++i) {
    worst = std::max({worst, std::abs(double(tag.corners[i].x) - expected[i].x),
                      std::abs(double(tag.corners[i].y) - expected[i].y)});
  }
  return worst;
}

double MaxCornerError(const ArucoTag& tag, const Quad& expected) {
  double worst = 0.0;
  for (int i = 0; i < 4; ++i) worst = std::max(worst, cv::norm(cv::Point2d(tag.corners[i]) - cv::Point2d(expected[i])));
  return worst;
}

const ArucoTag* Find(const std::vector<ArucoTag>& tags, int id) {
  const auto it = std::find_if(tags.begin(), tags.end(), [id](const ArucoTag& t) { return t.id == id; });
  return it == tags.end() ? nullptr : &*it;
}

// OpenCV's test_arucodetection.cpp asserts these with default parameters to +-1 px.
const std::map<int, Quad> kSingleMarkers = {
    {40, {{{359, 310}, {404, 310}, {410, 350}, {362, 350}}}},
    {98, {{{427, 255}, {469, 256}, {477, 289}, {434, 288}}}},
    {62, {{{233, 273}, {190, 273}, {196, 241}, {237, 241}}}},
    {23, {{{298, 185}, {334, 186}, {335, 212}, {297, 211}}}},
    {124, {{{425, 163}, {430, 186}, {394, 186}, {390, 162}}}},
    {203, {{{195, 155}, {230, 155}, {227, 178}, {190, 178}}}},
};

TEST(RealPhotos, SingleMarkersIdsAndCornersWithOpenCvDefaults) {
  const auto tags = DetectIn("opencv_tutorial/singlemarkersoriginal.jpg", "DICT_6X6_250", CornerRefinement::kNone);
  ASSERT_EQ(Ids(tags), (std::multiset<int>{23, 40, 62, 98, 124, 203}));
  for (const auto& [id, quad] : kSingleMarkers) {
    EXPECT_LE(MaxAxisError(*Find(tags, id), quad), 1.0) << "id " << id;
  }
}

// The asserted values are whole pixels of unrefined corners, so refined corners may sit a little
// further than 1 px from them while being closer to the truth.
TEST(RealPhotos, SingleMarkersCornersWithOurDefaultSubpixel) {
  const auto tags = DetectIn("opencv_tutorial/singlemarkersoriginal.jpg", "DICT_6X6_250", CornerRefinement::kSubpix);
  ASSERT_EQ(tags.size(), 6u);
  for (const auto& [id, quad] : kSingleMarkers) {
    ASSERT_NE(Find(tags, id), nullptr) << id;
    EXPECT_LE(MaxAxisError(*Find(tags, id), quad), 1.5) << "id " << id;
  }
}

TEST(RealPhotos, CharucoBoardHasExactly17Markers) {
  const auto tags = DetectIn("opencv_tutorial/choriginal.jpg", "DICT_6X6_250", CornerRefinement::kSubpix);
  std::multiset<int> expected;
  for (int id = 0; id <= 16; ++id) expected.insert(id);
  EXPECT_EQ(Ids(tags), expected);
}

TEST(RealPhotos, OccludedCharucoReportsOnlyVisibleMarkers) {
  for (auto refine : {CornerRefinement::kNone, CornerRefinement::kSubpix}) {
    const auto tags = DetectIn("opencv_tutorial/chocclusion_original.jpg", "DICT_6X6_250", refine);
    EXPECT_EQ(Ids(tags), (std::multiset<int>{0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 12, 15}));
    for (int hidden : {11, 13, 14, 16}) EXPECT_EQ(Find(tags, hidden), nullptr) << hidden;
  }
}

// UbiquityRobotics/fiducials asserts these (exact floats from OpenCV's sub-pixel refinement).
TEST(RealPhotos, FiducialsSubpixelCornersWithin005Px) {
  const auto one = DetectIn("ubiquity_fiducials/tag_01_d7_14cm.png", "DICT_5X5_1000", CornerRefinement::kSubpix);
  ASSERT_EQ(Ids(one), (std::multiset<int>{1}));
  EXPECT_LE(MaxCornerError(one[0], {{{569.89917f, 201.55890f}, {777.42560f, 206.85025f}, {767.95856f, 415.37830f},
                                     {565.75311f, 409.24496f}}}),
            0.05);

  const auto two = DetectIn("ubiquity_fiducials/tag_245-246_d7_14cm.png", "DICT_5X5_1000", CornerRefinement::kSubpix);
  ASSERT_EQ(Ids(two), (std::multiset<int>{245, 246}));
  EXPECT_LE(MaxCornerError(*Find(two, 245), {{{307.68246f, 157.38346f}, {545.10131f, 167.04420f},
                                              {540.11614f, 403.27578f}, {305.64746f, 395.01422f}}}),
            0.05);
  EXPECT_LE(MaxCornerError(*Find(two, 246), {{{671.51892f, 173.46070f}, {900.29650f, 178.44973f},
                                              {895.06933f, 407.39855f}, {666.39910f, 403.12911f}}}),
            0.05);
}

CameraModel RaspiCam() {
  return CameraModel::FromIntrinsics(
      cv::Matx33d(1006.126285753055, 0, 655.8639244150409, 0, 1004.015433012594, 490.6140221242933, 0, 0, 1),
      {0.1349735087283542, -0.2335869827451621, 0.0006697030315075139, 0.004846737465872353, 0.0});
}

TEST(RealPhotos, FiducialsPnpDistance) {
  DetectorConfig config;
  config.dictionary = "DICT_5X5_1000";
  config.default_side_length = 0.145;
  const Detector detector(config);

  auto one = Detect(test::LoadGrey("ubiquity_fiducials/tag_01_d7_14cm.png"), detector);
  ASSERT_EQ(one.size(), 1u);
  ASSERT_TRUE(EstimatePoseFromPNP(RaspiCam(), one[0]));
  EXPECT_EQ(one[0].pose_source, PoseSource::kPnp);
  EXPECT_NEAR(one[0].distance, 0.73, 0.02);
  EXPECT_LT(one[0].reprojection_error, 0.5);
  // Its centre is at about x = 670 px against cx = 656 px: a little right of the optical axis.
  EXPECT_GT(one[0].yaw, 0.0);
  EXPECT_LT(one[0].yaw, 0.05);

  auto two = Detect(test::LoadGrey("ubiquity_fiducials/tag_245-246_d7_14cm.png"), detector);
  ASSERT_EQ(two.size(), 2u);
  for (auto& tag : two) {
    ASSERT_TRUE(EstimatePoseFromPNP(RaspiCam(), tag));
    EXPECT_NEAR(tag.distance, 0.66, 0.03) << tag.id;
  }
  // 245 is on the left of the image, 246 on the right: bearings have opposite signs.
  EXPECT_LT(Find(two, 245)->yaw, 0.0);
  EXPECT_GT(Find(two, 246)->yaw, 0.0);
}

}  // namespace
}  // namespace arucotag

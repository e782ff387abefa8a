#include "photos.hpp"

#include <opencv2/calib3d.hpp>
#include <opencv2/imgcodecs.hpp>

#include "rig.hpp"

namespace arucotag::test {

const Photo& TwoTags() {
  static const Photo photo{cv::imread(std::string(ARUCOTAG_TEST_DATA) + "/ubiquity_fiducials/tag_245-246_d7_14cm.png"),
                           {{245, {{{307.68246, 157.38346}, {545.10131, 167.04420}, {540.11614, 403.27578},
                                    {305.64746, 395.01422}}}},
                            {246, {{{671.51892, 173.46070}, {900.29650, 178.44973}, {895.06933, 407.39855},
                                    {666.39910, 403.12911}}}}}};
  return photo;
}

const Photo& OneTag() {
  static const Photo photo{cv::imread(std::string(ARUCOTAG_TEST_DATA) + "/ubiquity_fiducials/tag_01_d7_14cm.png"),
                           {{1, {{{569.89917, 201.55890}, {777.42560, 206.85025}, {767.95856, 415.37830},
                                  {565.75311, 409.24496}}}}}};
  return photo;
}

void ReferencePose(const Quad& corners, cv::Matx33d& rotation, cv::Vec3d& position, const cv::Matx33d& k,
                   const std::vector<double>& d) {
  const double h = kPhotoSide / 2.0;
  const std::vector<cv::Point3d> object{{-h, h, 0.0}, {h, h, 0.0}, {h, -h, 0.0}, {-h, -h, 0.0}};
  const std::vector<cv::Point2d> image(corners.begin(), corners.end());
  cv::Vec3d rvec;
  cv::solvePnP(object, image, k, d, rvec, position, false, cv::SOLVEPNP_IPPE_SQUARE);
  cv::Rodrigues(rvec, rotation);
}

sensor_msgs::CameraInfoPtr RaspiInfo(const ros::Time& stamp, const std::string& frame, const cv::Matx33d& k,
                                     const std::vector<double>& d) {
  auto info = boost::make_shared<sensor_msgs::CameraInfo>();
  info->header.stamp = stamp;
  info->header.frame_id = frame;
  info->width = 1280;
  info->height = 960;
  info->distortion_model = "plumb_bob";
  info->D = d;
  for (int i = 0; i < 9; ++i) info->K[i] = k.val[i];
  info->R = {1, 0, 0, 0, 1, 0, 0, 0, 1};
  for (int r = 0; r < 3; ++r)
    for (int c = 0; c < 3; ++c) info->P[r * 4 + c] = k(r, c);
  return info;
}

sensor_msgs::ImagePtr PhotoImage(const Photo& photo, const ros::Time& stamp, const std::string& frame) {
  auto image = Rig::ImageMessage(photo.bgr, stamp);
  image->header.frame_id = frame;
  return image;
}

}  // namespace arucotag::test

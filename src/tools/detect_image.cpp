// detect_image: runs the arucotag core on image files and prints what it finds.
//
//   detect_image [--dictionary DICT_4X4_50] [--size 0.15] [--camera FILE] [--refine subpix]
//                [--equalize] [--output DIR] IMAGE...
//
// --camera takes a ROS camera_info yaml (camera_calibration_parsers) or an OpenCV calibration yml
// (camera_matrix, distortion_coefficients). Without it only ids and corners are printed.
#include <cstdio>
#include <filesystem>
#include <iostream>
#include <optional>
#include <string>
#include <vector>

#include <camera_calibration_parsers/parse.h>
#include <opencv2/core/persistence.hpp>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>
#include <sensor_msgs/CameraInfo.h>

#include <arucotag/arucotag.hpp>

namespace {

void Usage() {
  std::cerr << "usage: detect_image [--dictionary NAME] [--size M] [--camera FILE] [--refine none|subpix|contour|"
               "apriltag] [--equalize] [--output DIR] IMAGE...\n";
}

// OpenCV's own calibration files carry `camera_matrix` as an opencv-matrix; ROS files carry a map.
std::optional<arucotag::CameraModel> ReadOpenCvCalibration(const std::string& path) {
  try {
    cv::FileStorage fs(path, cv::FileStorage::READ);
    if (!fs.isOpened()) return std::nullopt;
    cv::Mat K, D;
    fs["camera_matrix"] >> K;
    fs["distortion_coefficients"] >> D;
    if (K.rows != 3 || K.cols != 3) return std::nullopt;
    K.convertTo(K, CV_64F);
    std::vector<double> distortion;
    if (!D.empty()) D.reshape(1, 1).convertTo(distortion, CV_64F);
    return arucotag::CameraModel::FromIntrinsics(cv::Matx33d(K), distortion);
  } catch (const cv::Exception&) {
    return std::nullopt;
  }
}

arucotag::CameraModel ReadCamera(const std::string& path) {
  if (auto camera = ReadOpenCvCalibration(path)) return *camera;
  std::string name;
  sensor_msgs::CameraInfo info;
  if (!camera_calibration_parsers::readCalibration(path, name, info)) {
    throw arucotag::Error("cannot read camera file '" + path + "' as OpenCV or ROS calibration");
  }
  if (info.distortion_model == "equidistant") {  // fisheye: k1..k4 of cv::fisheye
    return arucotag::CameraModel::FromFisheye(cv::Matx33d(info.K.data()), info.D);
  }
  return arucotag::CameraModel::FromIntrinsics(cv::Matx33d(info.K.data()), info.D);
}

}  // namespace

int main(int argc, char** argv) {
  arucotag::DetectorConfig config;
  arucotag::PreprocessOptions preprocess;
  std::optional<arucotag::CameraModel> camera;
  std::string output_dir = ".";
  std::vector<std::string> images;
  try {
    for (int i = 1; i < argc; ++i) {
      const std::string arg = argv[i];
      const auto value = [&]() -> std::string {
        if (i + 1 >= argc) throw arucotag::Error("missing value after " + arg);
        return argv[++i];
      };
      if (arg == "--dictionary") {
        config.dictionary = value();
      } else if (arg == "--size") {
        config.default_side_length = std::stod(value());
      } else if (arg == "--camera") {
        camera = ReadCamera(value());
        camera->Validate();
      } else if (arg == "--refine") {
        config.corner_refinement = arucotag::CornerRefinementFromName(value());
      } else if (arg == "--equalize") {
        preprocess.equalize = true;
      } else if (arg == "--output") {
        output_dir = value();
      } else if (arg == "-h" || arg == "--help") {
        Usage();
        return 0;
      } else if (!arg.empty() && arg[0] == '-') {
        throw arucotag::Error("unknown option " + arg);
      } else {
        images.push_back(arg);
      }
    }
    if (images.empty()) {
      Usage();
      return 2;
    }
    std::filesystem::create_directories(output_dir);
    const arucotag::Detector detector(config);

    int failures = 0;
    for (const auto& path : images) {
      const cv::Mat image = cv::imread(path, cv::IMREAD_UNCHANGED);
      if (image.empty()) {
        std::cerr << path << ": cannot read image\n";
        ++failures;
        continue;
      }
      cv::Mat grey;
      arucotag::PreprocessFrame(image, grey, preprocess);
      // With a camera the image is taken as raw (unrectified): markers its lens bends keep the edge fit.
      std::vector<arucotag::ArucoTag> tags =
          camera ? arucotag::Detect(grey, detector, *camera) : arucotag::Detect(grey, detector);
      std::printf("%s: %zu tag(s)\n", path.c_str(), tags.size());
      for (auto& tag : tags) {
        std::printf("  id %d corners", tag.id);
        for (const auto& c : tag.corners) std::printf(" (%.2f,%.2f)", c.x, c.y);
        if (camera && arucotag::EstimatePoseFromPNP(*camera, tag)) {
          std::printf(" distance %.3f m yaw %.2f deg t [%.3f %.3f %.3f] m rvec [%.3f %.3f %.3f] rms %.2f px",
                      tag.distance, tag.yaw * 180.0 / CV_PI, tag.tvec[0], tag.tvec[1], tag.tvec[2], tag.rvec[0],
                      tag.rvec[1], tag.rvec[2], tag.reprojection_error);
        }
        std::printf("\n");
      }
      cv::Mat overlay;
      if (image.channels() == 3 && image.depth() == CV_8U) {
        overlay = image.clone();
      } else {
        cv::cvtColor(grey, overlay, cv::COLOR_GRAY2BGR);
      }
      arucotag::DrawDetections(overlay, tags);
      const auto out = std::filesystem::path(output_dir) / (std::filesystem::path(path).stem().string() + "_overlay.png");
      cv::imwrite(out.string(), overlay);
      std::printf("  overlay: %s\n", out.c_str());
    }
    return failures == 0 ? 0 : 1;
  } catch (const std::exception& e) {
    std::cerr << "detect_image: " << e.what() << "\n";
    return 2;
  }
}

#pragma once

#include <map>
#include <string>
#include <vector>

#include <opencv2/aruco.hpp>
#include <opencv2/core.hpp>

#include <arucotag/aruco_tag.hpp>

namespace arucotag {

/// How cv::aruco refines corner positions after finding a candidate square.
enum class CornerRefinement { kNone, kSubpix, kContour, kApriltag };

/// Parses "none", "subpix", "contour" or "apriltag"; throws arucotag::Error otherwise.
CornerRefinement CornerRefinementFromName(const std::string& name);

/// Everything the detector needs, as plain values so it can be filled from yaml, the command line or
/// dynamic_reconfigure. Defaults are OpenCV's, except corner refinement (sub-pixel, which PnP needs)
/// and the dictionary and size (a URC post: DICT_4X4_50, 0.15 m black square).
struct DetectorConfig {
  std::string dictionary = "DICT_4X4_50";  ///< any OpenCV predefined name, see DictionaryNames()
  CornerRefinement corner_refinement = CornerRefinement::kSubpix;

  // cv::aruco::DetectorParameters, same meaning and defaults as OpenCV 4.6.
  int adaptive_thresh_win_size_min = 3;
  int adaptive_thresh_win_size_max = 23;
  int adaptive_thresh_win_size_step = 10;
  double adaptive_thresh_constant = 7.0;
  double min_marker_perimeter_rate = 0.03;
  double max_marker_perimeter_rate = 4.0;
  double polygonal_approx_accuracy_rate = 0.03;
  double min_corner_distance_rate = 0.05;
  int min_distance_to_border = 3;
  double min_marker_distance_rate = 0.05;
  int marker_border_bits = 1;
  int perspective_remove_pixel_per_cell = 4;
  double perspective_remove_ignored_margin_per_cell = 0.13;
  double max_erroneous_bits_in_border_rate = 0.35;
  double min_otsu_std_dev = 5.0;
  double error_correction_rate = 0.6;
  int corner_refinement_win_size = 5;
  int corner_refinement_max_iterations = 30;
  double corner_refinement_min_accuracy = 0.01;
  bool detect_inverted_marker = false;

  std::vector<int> allowed_ids;  ///< when not empty, only these ids are reported
  std::vector<int> ignored_ids;  ///< never reported (applied after allowed_ids)
  double default_side_length = 0.15;   ///< m, for ids not in side_lengths
  std::map<int, double> side_lengths;  ///< m, per id
};

/// All OpenCV predefined dictionary names, e.g. "DICT_4X4_50", "DICT_APRILTAG_36h11".
const std::vector<std::string>& DictionaryNames();

/// Maps a dictionary name to cv::aruco::PREDEFINED_DICTIONARY_NAME; throws arucotag::Error listing
/// the valid names on an unknown one.
int DictionaryFromName(const std::string& name);

/// Owns the cv::aruco dictionary and parameters built from a DetectorConfig. Construction validates
/// the whole configuration and throws arucotag::Error naming the first bad field, so a running
/// pipeline can swap in a new Detector only once it is known to be good.
class Detector {
 public:
  explicit Detector(const DetectorConfig& config = {});

  const DetectorConfig& config() const { return config_; }
  const cv::Ptr<cv::aruco::Dictionary>& dictionary() const { return dictionary_; }
  const cv::Ptr<cv::aruco::DetectorParameters>& parameters() const { return parameters_; }

  /// Side length (m) configured for an id.
  double SideLength(int id) const;
  /// Whether the allow- and ignore-lists let this id through.
  bool Accepts(int id) const;

 private:
  DetectorConfig config_;
  cv::Ptr<cv::aruco::Dictionary> dictionary_;
  cv::Ptr<cv::aruco::DetectorParameters> parameters_;
};

/// Finds the markers in an 8-bit frame (grey, as PreprocessFrame makes it, or 3-channel BGR, which
/// is converted). Returns one ArucoTag per marker that passes the id lists, with id, corners and side
/// length set and no pose. Throws arucotag::Error on an empty frame or one that is not 8-bit with
/// 1 or 3 channels.
std::vector<ArucoTag> Detect(const cv::Mat& frame, const Detector& detector);

}  // namespace arucotag

#pragma once

#include <map>
#include <memory>
#include <string>
#include <vector>

#include <opencv2/aruco.hpp>
#include <opencv2/core.hpp>

#include <arucotag/aruco_tag.hpp>

namespace arucotag {

struct CameraModel;  // pose.hpp

/// How corner positions are refined after a candidate square is found. kEdge (ours, the default)
/// fits lines to sub-pixel edge points near each corner (RefineCornersOnEdges); the others are
/// cv::aruco's. On exactly rendered markers kEdge lands within a few hundredths of a pixel where
/// cv::aruco's sub-pixel refinement is 0.2 px inwards (and pixels off on small markers).
enum class CornerRefinement { kNone, kSubpix, kContour, kApriltag, kEdge };

/// Parses "none", "subpix", "contour", "apriltag" or "edge"; throws arucotag::Error otherwise.
CornerRefinement CornerRefinementFromName(const std::string& name);

/// The name CornerRefinementFromName parses back to `refinement`.
const char* CornerRefinementName(CornerRefinement refinement);

/// Everything the detector needs, as plain values so it can be filled from yaml, the command line or
/// dynamic_reconfigure. Defaults are OpenCV's, except corner refinement (edge fit, which PnP needs)
/// and the dictionary and size (a URC post: DICT_4X4_50, 0.15 m black square).
struct DetectorConfig {
  std::string dictionary = "DICT_4X4_50";  ///< any OpenCV predefined name, see DictionaryNames()
  CornerRefinement corner_refinement = CornerRefinement::kEdge;

  // cv::aruco::DetectorParameters, same meaning and defaults as OpenCV 4.6.
  int adaptive_thresh_win_size_min = 3;
  int adaptive_thresh_win_size_max = 23;   ///< at most 1001 px
  int adaptive_thresh_win_size_step = 10;  ///< at most 200 windows from min to max
  double adaptive_thresh_constant = 7.0;  ///< grey levels, -255 to 255
  double min_marker_perimeter_rate = 0.03;
  double max_marker_perimeter_rate = 4.0;  ///< at most 16 (past 4 it changes nothing)
  double polygonal_approx_accuracy_rate = 0.03;
  double min_corner_distance_rate = 0.05;
  int min_distance_to_border = 3;
  double min_marker_distance_rate = 0.05;
  int marker_border_bits = 1;
  /// (marker bits + 2 * marker_border_bits) * this is at most 1440 px
  int perspective_remove_pixel_per_cell = 4;
  double perspective_remove_ignored_margin_per_cell = 0.13;
  double max_erroneous_bits_in_border_rate = 0.35;
  double min_otsu_std_dev = 5.0;
  double error_correction_rate = 0.6;
  int corner_refinement_win_size = 5;         ///< px, 1-60
  int corner_refinement_max_iterations = 30;  ///< 1-400
  double corner_refinement_min_accuracy = 0.01;
  bool detect_inverted_marker = false;  ///< not with corner_refinement kApriltag (OpenCV 4.6 crashes)

  /// Multi-scale search (one threshold window per pyramid level, all cores) whose candidates are
  /// decoded on the full frame as cv::aruco decodes them and start refinement from cv::aruco's own
  /// corners: the same ids and corners as the full search (cv::aruco::detectMarkers with this
  /// configuration; test_fast_path.cpp checks 0.1 px on the real photos) in a fraction of the time.
  /// Under about 15 px it can differ both ways: on rendered 12-30 px markers it missed 3 of 217 the
  /// full search found (no candidate there) and found 5 it did not. Serves corner_refinement "edge"
  /// and "subpix" with black markers; other settings, or false, run cv::aruco::detectMarkers itself.
  /// Both paths give candidates under 30 px that cv::aruco's reading rejects a second chance (cells
  /// estimated from every pixel they touch, one code matched within the few cells a random pattern
  /// would rarely come that close by (2 for tag36h11, none for DICT_4X4_50), a quiet zone, and the
  /// fitted pattern must explain the pixels): tiny and steeply tilted markers cv::aruco misses are found (a 0.15 m
  /// marker at 10 m, 60 degrees; test_small_markers.cpp), with no more false positives than
  /// cv::aruco's own. Such markers are refined like the others with "edge" and "subpix"; with
  /// "contour" and "apriltag" they keep the decoder's corners (and "apriltag"'s candidate search
  /// does not find the steepest ones).
  bool fast_path = true;
  /// With fast_path: successive Detect calls on one Detector are frames of one video stream. A marker
  /// of the previous frame is then first read where it is predicted (constant velocity), without a
  /// search; only the regions of markers that do not read there (or were lost a few frames ago) and a
  /// band along the image edge the scene moves in from are searched, and the whole frame once every
  /// full_search_interval frames: a marker that appears away from that edge is reported within
  /// full_search_interval frames. A frame with nothing tracked, that does not look like the next one
  /// (other size or content), or where a tracked marker is lost, is searched whole. Set false, or
  /// call ResetTracking(), when consecutive calls are unrelated images that may share markers.
  bool tracking = true;
  int full_search_interval = 8;  ///< frames, >= 1: the full scan's budget, a bound on the delay before a new marker is found

  /// With corner_refinement kEdge: markers whose mean side is shorter than this (px) are refined
  /// further by fitting their whole decoded pattern (RefineCornersOnPattern), 0.25-0.8 ms each. On
  /// rendered markers the edge fit alone leaves a median corner error about twice the fit's from 30 px
  /// up (0.018 against 0.010 px), four times under 20 px, where PnP poses flip without the fit
  /// (a 0.15 m marker at 6-15 m: 104 flips in 523 poses, against 20). 0 turns it off. The fit's
  /// model has straight edges: on a raw frame, Detect(frame, detector, lens) leaves the markers the
  /// lens bends to the edge fit. ArucoTag::pattern_fitted tells which markers it placed. Markers of
  /// pattern_fit_sharp_max_side or more get it only where their edges are blurred.
  int pattern_fit_max_side = 56;
  /// With the pattern fit: markers from this side (px, 32-256) up to pattern_fit_max_side get the fit
  /// only where their edges are blurred (a ramp variance across them of kSharpEdgeVariance px^2 or
  /// more); sharp ones keep the edge fit's corners. At or above pattern_fit_max_side every marker
  /// under that gets the fit. Measured at 40 (stop 51): a tenth of Detect's instructions off 720p
  /// frames of tag36h11 markers and a sixth off 640x480 frames of five (callgrind; 8-9 % of the time), where renders
  /// (0.5 px Gaussian, ramp variance 0.39-0.50 px^2) leave 40-56 px markers a median corner error of
  /// 0.011-0.025 px with the edge fit alone. On the sample recording's motion-blurred jpeg frames
  /// (0.67-1.24 px^2) the post faces keep the fit: there the edge fit alone took a face's position
  /// NEES over the replay test's 6 (6.6 with every 40-56 px marker left to it).
  int pattern_fit_sharp_max_side = 40;
  /// At most this many markers per frame get the pattern fit, the smallest first (they need it
  /// most): bounds the time a crowded frame (a calibration board, a wall of markers) adds. 0 = no
  /// limit. A small marker read by the second chance (see fast_path) keeps the pattern fit that
  /// checked its reading, fitted once, and does not count.
  int pattern_fit_max_markers = 8;
  /// With fast_path: the most threads one Detect call runs its own loops on (the candidate search's
  /// strips, decoding, refinement): a CPU budget for the detector that leaves the other cores to the
  /// rest of the stack. 1 runs them on the calling thread alone. 0 = as many as OpenCV's thread
  /// count (cv::getNumThreads(), process-wide). The full-resolution level is searched in this many
  /// strips (OpenCV's count for 0), with what crosses a seam between them searched again: the markers,
  /// their corners and their order are the same to the bit at any setting and any OpenCV thread count,
  /// save a marker across a seam so big that its neighbourhood covers over half the frame (it is not
  /// searched again; its corners can move by hundredths of a pixel).
  /// cv::aruco's own search (fast_path false) uses OpenCV's count.
  int threads = 0;

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

/// The cells of marker `id` including `border_bits` of black border on each side, as a square
/// CV_8UC1 matrix in the marker's own orientation (row 0 along the top edge, TL to TR), 1 = black,
/// 0 = white. Throws arucotag::Error when the id is not in the dictionary.
cv::Mat MarkerCells(const cv::aruco::Dictionary& dictionary, int id, int border_bits = 1);

/// Owns the cv::aruco dictionary and parameters built from a DetectorConfig. Construction validates
/// the whole configuration and throws arucotag::Error naming the first bad field, so a running
/// pipeline can swap in a new Detector only once it is known to be good.
class Detector {
 public:
  explicit Detector(const DetectorConfig& config = {});
  /// A copy has the same configuration and starts without tracked markers.
  Detector(const Detector& other);
  Detector& operator=(const Detector& other);
  Detector(Detector&& other) noexcept;
  Detector& operator=(Detector&& other) noexcept;
  ~Detector();

  const DetectorConfig& config() const { return config_; }
  const cv::Ptr<cv::aruco::Dictionary>& dictionary() const { return dictionary_; }
  const cv::Ptr<cv::aruco::DetectorParameters>& parameters() const { return parameters_; }

  /// Side length (m) configured for an id.
  double SideLength(int id) const;
  /// Whether the allow- and ignore-lists let this id through.
  bool Accepts(int id) const;

  /// Forgets the markers tracked from earlier frames: the next Detect searches the whole frame.
  /// Thread-safe.
  void ResetTracking() const;

  /// Frames this Detector searched whole, and frames it searched only where tracking pointed; of
  /// the tracked markers, how many were read where they were predicted (without a search); and the
  /// pixels thresholded and traced over all frames (at their pyramid level's resolution).
  struct TrackingStats {
    unsigned long long full_searches = 0, tracked_frames = 0;
    unsigned long long read_at_prediction = 0, searched_pixels = 0;
  };
  TrackingStats tracking_stats() const;

 private:
  friend std::vector<ArucoTag> Detect(const cv::Mat& frame, const Detector& detector, const CameraModel& lens);
  struct Tracking;  // the tracked markers of the last frame, behind a mutex (detector.cpp)

  DetectorConfig config_;
  cv::Ptr<cv::aruco::Dictionary> dictionary_;
  cv::Ptr<cv::aruco::DetectorParameters> parameters_;
  // Detect takes the Detector const (callers share one across threads); the tracking state is the
  // one thing a call changes, and it guards itself.
  std::unique_ptr<Tracking> tracking_;
};

/// Finds the markers in an 8-bit frame (grey, as PreprocessFrame makes it, or 3-channel BGR, which
/// is converted). Returns one ArucoTag per marker that passes the id lists, with id, corners and side
/// length set and no pose. Throws arucotag::Error on an empty frame, one that is not 8-bit with
/// 1 or 3 channels, or one OpenCV cannot search with this configuration (a corner refinement window
/// wider than the frame, say). With config().fast_path and tracking (the defaults) it uses and updates the
/// Detector's tracked markers (see DetectorConfig::tracking); safe to call from several threads. The
/// markers, their corners and their order do not depend on the number of threads it runs on (see
/// DetectorConfig::threads for the one exception).
std::vector<ArucoTag> Detect(const cv::Mat& frame, const Detector& detector);

/// Detect for a frame taken through `lens` without rectification (a raw image and its camera
/// model). The whole-pattern fit (DetectorConfig::pattern_fit_max_side) models a marker as a
/// homography of its grid, whose edges are straight; a lens that bends a marker's edges by
/// kMaxPatternFitBend px or more moves its fitted corners by about twice that, where the edge fit,
/// fitted next to each corner, follows the bend. Such markers keep the edge fit's corners, and do
/// not count against pattern_fit_max_markers. A lens without distortion bends nothing: the same
/// result as Detect(frame, detector) (such a lens is not looked at further). Throws arucotag::Error
/// as Detect does, and where a lens with distortion fails CameraModel::Validate.
std::vector<ArucoTag> Detect(const cv::Mat& frame, const Detector& detector, const CameraModel& lens);

/// px: how far a lens may bend a marker's edge (the distance of the edge's middle from the chord
/// between its corners) for the whole-pattern fit to run on it. Measured on 640x480 renders through
/// radial (k1 0 to -0.2, 90 degrees) and fisheye lenses, markers of 12-56 px, 4.2 k markers: the
/// pattern fit's worst corner is off by about twice the bend, and does worse than the edge fit on
/// half the markers from 0.04 px on.
inline constexpr double kMaxPatternFitBend = 0.04;

/// The ramp variance (px^2) across a marker's edges under which DetectorConfig::pattern_fit_sharp_max_side
/// counts them sharp: between the renders' 0.39-0.50 (0.5 px Gaussian blur, pixel and bilinear
/// reading included) and the sample recording's 0.67-1.24 (motion blur, jpeg).
inline constexpr double kSharpEdgeVariance = 0.6;

}  // namespace arucotag

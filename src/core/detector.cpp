#include <arucotag/detector.hpp>
#include <arucotag/pose.hpp>
#include <arucotag/refine.hpp>

#include <algorithm>
#include <cmath>
#include <limits>
#include <sstream>

#include <opencv2/imgproc.hpp>

#include "decode_small.hpp"
#include "fast_detect.hpp"
#include "geometry.hpp"
#include "identify.hpp"
#include "parallel.hpp"
#include "refine_corner.hpp"
#include "refine_edges.hpp"
#include "refine_pattern.hpp"

namespace arucotag {

struct Detector::Tracking : internal::TrackingState {};

namespace {

// Whether `lens` bends straight lines: any distortion coefficient not zero, or a fisheye (r = f
// theta even with all its coefficients zero).
bool Bends(const CameraModel& lens) {
  return lens.distortion_model == DistortionModel::kEquidistant ||
         std::any_of(lens.distortion.begin(), lens.distortion.end(), [](double k) { return k != 0.0; });
}

// How far (px) `lens` bends the marker's edges: the largest distance of an edge's middle from the
// chord between its corners, the middle being where the straight line between the corners' rays
// (undistorted) projects halfway. The chords' ends are the corners projected back too, so that
// undistortion's round-off leaves the chord and the middle alike. Infinity where OpenCV cannot
// undistort a corner (a fisheye corner 90 degrees off axis).
double EdgeBend(const CameraModel& lens, const std::array<cv::Point2f, 4>& corners) {
  const std::vector<cv::Point2d> rays = lens.Normalize({corners.begin(), corners.end()});
  std::vector<cv::Point3d> points;
  for (int i = 0; i < 4; ++i) points.emplace_back(rays[i].x, rays[i].y, 1.0);
  for (int i = 0; i < 4; ++i) {
    const cv::Point2d middle = 0.5 * (rays[i] + rays[(i + 1) % 4]);
    points.emplace_back(middle.x, middle.y, 1.0);
  }
  for (const auto& p : points) {
    if (!std::isfinite(p.x) || !std::isfinite(p.y) || std::abs(p.x) > 1e5 || std::abs(p.y) > 1e5) {
      return std::numeric_limits<double>::infinity();
    }
  }
  const std::vector<cv::Point2d> image = lens.Project(points, cv::Vec3d(0, 0, 0), cv::Vec3d(0, 0, 0));
  double bend = 0.0;
  for (int i = 0; i < 4; ++i) {
    const cv::Point2d a = image[i], chord = image[(i + 1) % 4] - a;
    const double length = cv::norm(chord);
    if (!(length > 0.0)) return std::numeric_limits<double>::infinity();
    bend = std::max(bend, std::abs(chord.cross(image[4 + i] - a)) / length);
  }
  return bend;
}

// Index = cv::aruco::PREDEFINED_DICTIONARY_NAME value.
const std::vector<std::string> kDictionaryNames = {
    "DICT_4X4_50",         "DICT_4X4_100",        "DICT_4X4_250",        "DICT_4X4_1000",
    "DICT_5X5_50",         "DICT_5X5_100",        "DICT_5X5_250",        "DICT_5X5_1000",
    "DICT_6X6_50",         "DICT_6X6_100",        "DICT_6X6_250",        "DICT_6X6_1000",
    "DICT_7X7_50",         "DICT_7X7_100",        "DICT_7X7_250",        "DICT_7X7_1000",
    "DICT_ARUCO_ORIGINAL", "DICT_APRILTAG_16h5",  "DICT_APRILTAG_25h9",  "DICT_APRILTAG_36h10",
    "DICT_APRILTAG_36h11",
};

// Bounds on the adaptive threshold windows: several times what dynamic_reconfigure allows (199 px,
// 197 windows), so only configs that would stall detection are refused.
constexpr int kMaxThresholdWindow = 1001;
constexpr int kMaxThresholdWindows = 200;
// Bound on the perimeter rates (perimeter / the frame's longer side): twice what dynamic_reconfigure
// allows (8). A quad inside the frame is at most 4 longer sides around, so any rate past 4 already
// means "no limit"; past the bound, rate * side overflows the detectors' int perimeters
// (fuzz_config: 1e300 in the fast path's search tasks).
constexpr double kMaxPerimeterRate = 16.0;
// Bounds on the corner refinement: twice what dynamic_reconfigure allows (30 px, 200 iterations).
// The fast path's cornerSubPix allocates and sweeps a (2 * win_size + 1)^2 window every iteration
// (fuzz_config: a window of 1.6e9 px threw std::length_error on a worker thread; large windows with
// thousands of iterations took seconds a corner).
constexpr int kMaxCornerWindow = 60;
constexpr int kMaxCornerIterations = 400;

void Require(bool ok, const char* field, const std::string& why) {
  if (!ok) {
    throw Error(std::string("detector parameter '") + field + "' " + why);
  }
}

bool Finite(double v) { return std::isfinite(v); }

void Validate(const DetectorConfig& c) {
  Require(c.adaptive_thresh_win_size_min >= 3, "adaptive_thresh_win_size_min", "must be >= 3");
  Require(c.adaptive_thresh_win_size_max >= c.adaptive_thresh_win_size_min, "adaptive_thresh_win_size_max",
          "must be >= adaptive_thresh_win_size_min");
  Require(c.adaptive_thresh_win_size_step > 0, "adaptive_thresh_win_size_step", "must be > 0");
  // Every window thresholds the whole frame, at a cost that grows with the window's size: without
  // a bound a config could hang Detect (fuzz_config found 2575 windows of up to 26000 px taking
  // minutes on a 160x120 frame) or overflow the window loop.
  Require(c.adaptive_thresh_win_size_max <= kMaxThresholdWindow, "adaptive_thresh_win_size_max",
          "must be <= " + std::to_string(kMaxThresholdWindow) + " px");
  const int windows = (c.adaptive_thresh_win_size_max - c.adaptive_thresh_win_size_min) / c.adaptive_thresh_win_size_step + 1;
  Require(windows <= kMaxThresholdWindows, "adaptive_thresh_win_size_step",
          "leaves more than " + std::to_string(kMaxThresholdWindows) + " threshold windows between min and max");
  // Grey levels; past +-255 it thresholds every pixel alike (and the fast path's cvFloor overflows).
  Require(Finite(c.adaptive_thresh_constant) && std::abs(c.adaptive_thresh_constant) <= 255.0,
          "adaptive_thresh_constant", "must be -255 to 255");
  Require(Finite(c.min_marker_perimeter_rate) && c.min_marker_perimeter_rate > 0.0, "min_marker_perimeter_rate",
          "must be > 0");
  Require(Finite(c.max_marker_perimeter_rate) && c.max_marker_perimeter_rate > c.min_marker_perimeter_rate,
          "max_marker_perimeter_rate", "must be > min_marker_perimeter_rate");
  // min_marker_perimeter_rate is below it, so bounded too.
  Require(c.max_marker_perimeter_rate <= kMaxPerimeterRate, "max_marker_perimeter_rate",
          "must be <= " + std::to_string(static_cast<int>(kMaxPerimeterRate)) +
              " (past 4, the perimeter of the whole frame, it changes nothing)");
  Require(Finite(c.polygonal_approx_accuracy_rate) && c.polygonal_approx_accuracy_rate > 0.0,
          "polygonal_approx_accuracy_rate", "must be > 0");
  Require(Finite(c.min_corner_distance_rate) && c.min_corner_distance_rate >= 0.0, "min_corner_distance_rate",
          "must be >= 0");
  Require(c.min_distance_to_border >= 0, "min_distance_to_border", "must be >= 0");
  Require(Finite(c.min_marker_distance_rate) && c.min_marker_distance_rate >= 0.0, "min_marker_distance_rate",
          "must be >= 0");
  Require(c.marker_border_bits >= 1, "marker_border_bits", "must be >= 1");
  Require(c.perspective_remove_pixel_per_cell >= 1, "perspective_remove_pixel_per_cell", "must be >= 1");
  Require(Finite(c.perspective_remove_ignored_margin_per_cell) && c.perspective_remove_ignored_margin_per_cell >= 0.0 &&
              c.perspective_remove_ignored_margin_per_cell < 0.5,
          "perspective_remove_ignored_margin_per_cell", "must be in [0, 0.5)");
  Require(Finite(c.max_erroneous_bits_in_border_rate) && c.max_erroneous_bits_in_border_rate >= 0.0 &&
              c.max_erroneous_bits_in_border_rate <= 1.0,
          "max_erroneous_bits_in_border_rate", "must be in [0, 1]");
  Require(Finite(c.min_otsu_std_dev) && c.min_otsu_std_dev >= 0.0, "min_otsu_std_dev", "must be >= 0");
  Require(Finite(c.error_correction_rate) && c.error_correction_rate >= 0.0 && c.error_correction_rate <= 1.0,
          "error_correction_rate", "must be in [0, 1]");
  // OpenCV 4.6's detectMarkers dereferences null with both (CORNER_REFINE_APRILTAG finds candidates
  // without the contours the inverted-marker reading then uses; fuzz_config).
  Require(!(c.corner_refinement == CornerRefinement::kApriltag && c.detect_inverted_marker), "detect_inverted_marker",
          "cannot be combined with corner_refinement apriltag (OpenCV's detectMarkers crashes on it)");
  Require(c.corner_refinement_win_size >= 1 && c.corner_refinement_win_size <= kMaxCornerWindow,
          "corner_refinement_win_size", "must be 1-" + std::to_string(kMaxCornerWindow) + " px");
  Require(c.corner_refinement_max_iterations >= 1 && c.corner_refinement_max_iterations <= kMaxCornerIterations,
          "corner_refinement_max_iterations", "must be 1-" + std::to_string(kMaxCornerIterations));
  Require(Finite(c.corner_refinement_min_accuracy) && c.corner_refinement_min_accuracy > 0.0,
          "corner_refinement_min_accuracy", "must be > 0");
  Require(c.full_search_interval >= 1, "full_search_interval", "must be >= 1 frame");
  Require(c.pattern_fit_max_side >= 0 && c.pattern_fit_max_side <= 256, "pattern_fit_max_side",
          "must be 0-256 px (0 turns the pattern fit off; larger markers need no pattern fit)");
  Require(c.pattern_fit_sharp_max_side >= 32 && c.pattern_fit_sharp_max_side <= 256, "pattern_fit_sharp_max_side",
          "must be 32-256 px (its edge blur measure reaches 2.5 px into the black border; at or above "
          "pattern_fit_max_side every marker under that gets the fit)");
  Require(c.pattern_fit_max_markers >= 0, "pattern_fit_max_markers", "must be >= 0 (0 = no limit)");
  Require(c.threads >= 0, "threads", "must be >= 0 (0 = OpenCV's thread count)");
  Require(Finite(c.default_side_length) && c.default_side_length > 0.0, "default_side_length", "must be > 0 m");
  for (const auto& [id, side] : c.side_lengths) {
    Require(Finite(side) && side > 0.0, "side_lengths",
            "must be > 0 m (id " + std::to_string(id) + " has " + std::to_string(side) + ")");
  }
}

int ToOpenCv(CornerRefinement refinement) {
  switch (refinement) {
    case CornerRefinement::kSubpix:
      return cv::aruco::CORNER_REFINE_SUBPIX;
    case CornerRefinement::kContour:
      return cv::aruco::CORNER_REFINE_CONTOUR;
    case CornerRefinement::kApriltag:
      return cv::aruco::CORNER_REFINE_APRILTAG;
    case CornerRefinement::kNone:
    case CornerRefinement::kEdge:  // refined by the core after cv::aruco
      break;
  }
  return cv::aruco::CORNER_REFINE_NONE;
}

}  // namespace

CornerRefinement CornerRefinementFromName(const std::string& name) {
  if (name == "none") return CornerRefinement::kNone;
  if (name == "subpix") return CornerRefinement::kSubpix;
  if (name == "contour") return CornerRefinement::kContour;
  if (name == "apriltag") return CornerRefinement::kApriltag;
  if (name == "edge") return CornerRefinement::kEdge;
  throw Error("unknown corner refinement '" + name + "' (valid: none, subpix, contour, apriltag, edge)");
}

const char* CornerRefinementName(CornerRefinement refinement) {
  switch (refinement) {
    case CornerRefinement::kSubpix:
      return "subpix";
    case CornerRefinement::kContour:
      return "contour";
    case CornerRefinement::kApriltag:
      return "apriltag";
    case CornerRefinement::kEdge:
      return "edge";
    case CornerRefinement::kNone:
      break;
  }
  return "none";
}

const std::vector<std::string>& DictionaryNames() { return kDictionaryNames; }

int DictionaryFromName(const std::string& name) {
  const auto it = std::find(kDictionaryNames.begin(), kDictionaryNames.end(), name);
  if (it == kDictionaryNames.end()) {
    std::ostringstream msg;
    msg << "unknown dictionary '" << name << "'; valid names:";
    for (const auto& valid : kDictionaryNames) msg << ' ' << valid;
    throw Error(msg.str());
  }
  return static_cast<int>(it - kDictionaryNames.begin());
}

Detector::Detector(const DetectorConfig& config) : config_(config), tracking_(std::make_unique<Tracking>()) {
  Validate(config_);
  dictionary_ = cv::aruco::getPredefinedDictionary(DictionaryFromName(config_.dictionary));
  // cv::aruco unwarps every candidate into a square this many pixels a side before reading its
  // bits (fuzz_config: 328 cells of 98 px asked for 1 GB per candidate).
  const long long unwarped_side =
      (dictionary_->markerSize + 2LL * config_.marker_border_bits) * config_.perspective_remove_pixel_per_cell;
  Require(unwarped_side <= internal::kMaxUnwarpedSide, "perspective_remove_pixel_per_cell",
          "times the marker's cells (" + config_.dictionary + " with marker_border_bits) must be <= " +
              std::to_string(internal::kMaxUnwarpedSide) + " px");
  parameters_ = cv::aruco::DetectorParameters::create();
  auto& p = *parameters_;
  p.adaptiveThreshWinSizeMin = config_.adaptive_thresh_win_size_min;
  p.adaptiveThreshWinSizeMax = config_.adaptive_thresh_win_size_max;
  p.adaptiveThreshWinSizeStep = config_.adaptive_thresh_win_size_step;
  p.adaptiveThreshConstant = config_.adaptive_thresh_constant;
  p.minMarkerPerimeterRate = config_.min_marker_perimeter_rate;
  p.maxMarkerPerimeterRate = config_.max_marker_perimeter_rate;
  p.polygonalApproxAccuracyRate = config_.polygonal_approx_accuracy_rate;
  p.minCornerDistanceRate = config_.min_corner_distance_rate;
  p.minDistanceToBorder = config_.min_distance_to_border;
  p.minMarkerDistanceRate = config_.min_marker_distance_rate;
  p.cornerRefinementMethod = ToOpenCv(config_.corner_refinement);
  p.cornerRefinementWinSize = config_.corner_refinement_win_size;
  p.cornerRefinementMaxIterations = config_.corner_refinement_max_iterations;
  p.cornerRefinementMinAccuracy = config_.corner_refinement_min_accuracy;
  p.markerBorderBits = config_.marker_border_bits;
  p.perspectiveRemovePixelPerCell = config_.perspective_remove_pixel_per_cell;
  p.perspectiveRemoveIgnoredMarginPerCell = config_.perspective_remove_ignored_margin_per_cell;
  p.maxErroneousBitsInBorderRate = config_.max_erroneous_bits_in_border_rate;
  p.minOtsuStdDev = config_.min_otsu_std_dev;
  p.errorCorrectionRate = config_.error_correction_rate;
  p.detectInvertedMarker = config_.detect_inverted_marker;
}

Detector::Detector(const Detector& other)
    : config_(other.config_),
      dictionary_(other.dictionary_),
      parameters_(other.parameters_),
      tracking_(std::make_unique<Tracking>()) {}

Detector& Detector::operator=(const Detector& other) {
  if (this != &other) {
    config_ = other.config_;
    dictionary_ = other.dictionary_;
    parameters_ = other.parameters_;
    tracking_ = std::make_unique<Tracking>();
  }
  return *this;
}

Detector::Detector(Detector&& other) noexcept = default;
Detector& Detector::operator=(Detector&& other) noexcept = default;
Detector::~Detector() = default;

void Detector::ResetTracking() const {
  if (!tracking_) return;
  std::lock_guard<std::mutex> lock(tracking_->mutex);
  tracking_->markers.clear();
  tracking_->thumbnail.release();
  tracking_->frames = 0;
  tracking_->since_full = 0;
}

Detector::TrackingStats Detector::tracking_stats() const {
  TrackingStats stats;
  if (!tracking_) return stats;
  std::lock_guard<std::mutex> lock(tracking_->mutex);
  stats.full_searches = tracking_->full_searches;
  stats.tracked_frames = tracking_->tracked_frames;
  stats.read_at_prediction = tracking_->read_at_prediction;
  stats.searched_pixels = tracking_->searched_pixels;
  return stats;
}

double Detector::SideLength(int id) const {
  const auto it = config_.side_lengths.find(id);
  return it == config_.side_lengths.end() ? config_.default_side_length : it->second;
}

bool Detector::Accepts(int id) const {
  const auto contains = [id](const std::vector<int>& ids) { return std::find(ids.begin(), ids.end(), id) != ids.end(); };
  if (!config_.allowed_ids.empty() && !contains(config_.allowed_ids)) return false;
  return !contains(config_.ignored_ids);
}

cv::Mat MarkerCells(const cv::aruco::Dictionary& dictionary, int id, int border_bits) {
  if (id < 0 || id >= dictionary.bytesList.rows) {
    throw Error("MarkerCells: id " + std::to_string(id) + " is not in the dictionary (0.." +
                std::to_string(dictionary.bytesList.rows - 1) + ")");
  }
  const int bits = dictionary.markerSize;
  cv::Mat cells(bits + 2 * border_bits, bits + 2 * border_bits, CV_8UC1, cv::Scalar(1));
  // getBitsFromByteList gives 1 for a white bit (drawMarker paints it 255).
  const cv::Mat white = cv::aruco::Dictionary::getBitsFromByteList(dictionary.bytesList.rowRange(id, id + 1), bits);
  cells(cv::Rect(border_bits, border_bits, bits, bits)).setTo(0, white);
  return cells;
}

std::vector<ArucoTag> Detect(const cv::Mat& frame, const Detector& detector) {
  static const CameraModel kNoLens;  // no distortion: bends nothing
  return Detect(frame, detector, kNoLens);
}

std::vector<ArucoTag> Detect(const cv::Mat& frame, const Detector& detector, const CameraModel& lens) {
  const bool bending = Bends(lens);
  if (bending) lens.Validate();
  if (frame.empty()) {
    throw Error("Detect: empty image");
  }
  if (frame.depth() != CV_8U || (frame.channels() != 1 && frame.channels() != 3)) {
    throw Error("Detect: want an 8-bit grey or BGR image (got " + std::to_string(frame.channels()) +
                " channel(s) of OpenCV depth " + std::to_string(frame.depth()) + "); run PreprocessFrame first");
  }
  // A configuration OpenCV cannot use on this frame (a corner window wider than the frame, an
  // approximation accuracy past the contour's size; fuzz_config) is refused with cv::Exception.
  try {
    cv::Mat grey = frame;
    if (frame.channels() == 3) {
      cv::cvtColor(frame, grey, cv::COLOR_BGR2GRAY);
    }
    std::vector<ArucoTag> tags;
    const auto add = [&](int id, const cv::Point2f* corners) {
      if (!detector.Accepts(id)) return false;
      ArucoTag tag;
      tag.id = id;
      std::copy_n(corners, 4, tag.corners.begin());
      tag.side_length = detector.SideLength(tag.id);
      tags.push_back(tag);
      return true;
    };
    // The fast path's pyramid needs a few pixels per level; frames too small to hold a findable marker
    // go to cv::aruco, which returns nothing for them.
    constexpr int kMinFastPathSide = 32;
    const bool fast = internal::FastPathSupports(detector.config()) && grey.cols >= kMinFastPathSide &&
                      grey.rows >= kMinFastPathSide;
    // Per tag: its pattern fit (last frame's for a marker read where tracking predicted it, then
    // this frame's) and whether its refinement confirmed it (a tracked marker is then read where
    // predicted next frame). char: written from parallel_for_.
    std::vector<char> anchored, edges_fitted;
    std::vector<internal::FitMemory> fits;
    // Per tag: the pattern fit that checked a small marker's reading (the second chance's), if any.
    std::vector<internal::FittedPattern> checked;
    if (fast) {
      // A moved-from Detector has no tracking state: it still detects, frame by frame.
      for (const auto& found : internal::FastDetect(grey, detector.config(), detector.dictionary(),
                                                    *detector.parameters(), detector.tracking_.get())) {
        if (!add(found.id, found.corners.data())) continue;
        fits.push_back(found.fit);
        edges_fitted.push_back(found.edges_fitted);
        checked.push_back(found.checked);
      }
    } else {
      std::vector<std::vector<cv::Point2f>> corners;
      std::vector<int> ids;
      // detectMarkers writes into the parameters it is given (4.6 resets the ArUco3 fields): give it a
      // copy so concurrent calls on one Detector never race.
      const auto parameters = cv::makePtr<cv::aruco::DetectorParameters>(*detector.parameters());
      // Sub-pixel refinement is the core's (below), with a window that fits the marker's cells.
      const bool subpix = detector.config().corner_refinement == CornerRefinement::kSubpix;
      if (subpix) parameters->cornerRefinementMethod = cv::aruco::CORNER_REFINE_NONE;
      std::vector<std::vector<cv::Point2f>> rejected;
      cv::aruco::detectMarkers(grey, detector.dictionary(), corners, ids, parameters, rejected);
      for (size_t i = 0; i < ids.size(); ++i) add(ids[i], corners[i].data());
      // Tiny markers whose cells cv::aruco's 4-px-per-cell reading blurs: the fast path decodes them
      // too, so both paths report the same ids.
      for (const auto& marker : internal::DecodeRejected(grey, rejected, corners, ids, *detector.dictionary(),
                                                         *parameters)) {
        if (!add(marker.id, marker.corners.data())) continue;
        checked.resize(tags.size() - 1);
        checked.push_back(marker.fit);
      }
      if (subpix) {
        const int cells = detector.dictionary()->markerSize + 2 * parameters->markerBorderBits;
        for (auto& tag : tags) {
          internal::RefineMarkerCorners(grey, tag.corners, cells, parameters->cornerRefinementWinSize,
                                        parameters->cornerRefinementMaxIterations,
                                        parameters->cornerRefinementMinAccuracy);
        }
      }
    }
    const DetectorConfig& config = detector.config();
    // Last frame's fits in, this frame's out: a tag that is not fitted this frame has none.
    fits.resize(tags.size());
    std::vector<internal::FitMemory> last(tags.size());
    last.swap(fits);
    edges_fitted.resize(tags.size(), 0);
    checked.resize(tags.size());
    anchored.assign(tags.size(), 1);
    if (config.corner_refinement == CornerRefinement::kEdge) {
      // Tags are independent: refine them on all cores (tens of microseconds each). Tracked markers
      // read at their prediction too: a pattern fit started from the prediction itself, skipping the
      // edge fit, was measured worse on the drive-by (corner error median 0.058 px, p95 0.46 px,
      // against 0.022 and 0.058 from the edge fit). One pass is enough for a marker whose pattern fit
      // carries last frame's offset (below), which takes up the edge fit's bias: the drive-by's
      // corner error stayed 0.022 / 0.059 px, with 5 % fewer instructions.
      const int cells = detector.dictionary()->markerSize + 2 * config.marker_border_bits;
      const auto carried = [&](size_t i) { return last[i].blur >= 0.0f; };
      internal::ParallelFor(cv::Range(0, static_cast<int>(tags.size())), config.threads, [&](const cv::Range& range) {
        for (int i = range.start; i < range.end; ++i) {
          if (edges_fitted[i]) continue;
          if (carried(i)) {
            internal::RefineCornersOnEdgesOnce(grey, tags[i].corners, cells);
          } else {
            RefineCornersOnEdges(grey, tags[i].corners, cells);
          }
        }
      });
      // A small marker whose reading a pattern fit checked (the second chance's) keeps that fit: it
      // is the fit this stage would run, from the decoder's corners instead of the edge fit's. It is
      // free, so it does not count against pattern_fit_max_markers.
      std::vector<char> fitted(tags.size(), 0);
      // Whether the lens leaves marker i's edges straight enough for a pattern fit (asked only of
      // markers that would get one: two OpenCV projections each).
      const auto straight = [&](size_t i) { return !bending || EdgeBend(lens, tags[i].corners) < kMaxPatternFitBend; };
      for (size_t i = 0; i < tags.size(); ++i) {
        if (checked[i].blur < 0.0f || !(internal::MeanSide(tags[i].corners) < config.pattern_fit_max_side) ||
            !straight(i)) {
          continue;
        }
        fits[i].blur = checked[i].blur;
        for (int c = 0; c < 4; ++c) fits[i].offset[c] = checked[i].corners[c] - tags[i].corners[c];
        tags[i].corners = checked[i].corners;
        tags[i].pattern_fitted = true;
        fitted[i] = 1;
      }
      // The other small markers, smallest first, up to pattern_fit_max_markers of them.
      std::vector<std::pair<float, size_t>> small;
      for (size_t i = 0; i < tags.size(); ++i) {
        const float side = internal::MeanSide(tags[i].corners);
        if (!fitted[i] && side < config.pattern_fit_max_side) small.emplace_back(side, i);
      }
      std::sort(small.begin(), small.end());
      // Whether a marker of pattern_fit_sharp_max_side or more has sharp edges, which leave it to the
      // edge fit (unmeasured edges keep the fit).
      const auto sharp = [&](const std::pair<float, size_t>& entry) {
        if (entry.first < config.pattern_fit_sharp_max_side) return false;
        const double ramp = internal::EdgeBlurVariance(grey, tags[entry.second].corners);
        return ramp >= 0.0 && ramp < kSharpEdgeVariance;
      };
      // The smallest the lens leaves straight and that are not sharp past pattern_fit_sharp_max_side, up to
      // pattern_fit_max_markers of them (asked in that order: the count bounds the questions too).
      const size_t most = config.pattern_fit_max_markers > 0 ? static_cast<size_t>(config.pattern_fit_max_markers)
                                                             : small.size();
      size_t kept = 0;
      for (size_t k = 0; k < small.size() && kept < most; ++k) {
        if (straight(small[k].second) && !sharp(small[k])) small[kept++] = small[k];
      }
      small.resize(kept);
      // A carried marker left out of the pattern fit this frame (grown past pattern_fit_max_side, or
      // past the count) takes its edge fit's second pass.
      for (const auto& entry : small) fitted[entry.second] = 1;
      for (size_t i = 0; i < tags.size(); ++i) {
        if (!edges_fitted[i] && carried(i) && !fitted[i]) internal::RefineCornersOnEdgesOnce(grey, tags[i].corners, cells);
      }
      // One marker's fit (small[k]); false when it is not trusted and the edge fit's corners stay. A
      // cold fit starts from `frame_blur` when it is known (below), else from kStartBlurVariances.
      float frame_blur = -1.0f;
      const auto fit = [&](size_t k) {
        const size_t i = small[k].second;
        ArucoTag& tag = tags[i];
        const cv::Mat black = MarkerCells(*detector.dictionary(), tag.id, config.marker_border_bits);
        // A tracked marker's fit starts from last frame's: its blur (one start instead of four),
        // and its corners where the edge fit puts them plus the offset the pattern fit added last
        // frame (the edge fit's bias changes little from frame to frame), so that one unverified
        // Gauss-Newton step usually ends it.
        const internal::FitMemory& before = last[i];
        const std::array<cv::Point2f, 4> edges = tag.corners;
        if (carried(i)) {
          for (int c = 0; c < 4; ++c) tag.corners[c] += before.offset[c];
        }
        float variance = carried(i) ? before.blur : frame_blur;
        anchored[i] = internal::RefineCornersOnPatternFrom(grey, black, tag.corners, variance,
                                                           carried(i) ? internal::kCarriedLastStep : internal::kColdLastStep);
        if (!anchored[i]) {
          tag.corners = edges;
          return false;
        }
        tag.pattern_fitted = true;
        fits[i].blur = variance;
        for (int c = 0; c < 4; ++c) fits[i].offset[c] = tag.corners[c] - edges[c];
        return true;
      };
      // The markers of one frame share its lens and focus: a cold fit starts from the blur variance
      // another fit of this frame found (one start instead of three or four), that of the largest
      // marker the second chance fitted, else that of the largest cold one here, fitted first. Which
      // fit leads depends on the markers alone, so the corners are the same at any thread count.
      // Callgrind of Detect (6 frames, 1 thread): 640x480/20 70.20 -> 67.11 M, /50 102.53 -> 100.45 M,
      // tag36h11 at 720p 88.36 -> 86.52 M, distant 117.86 -> 116.01 M; corner medians within 0.0002 px.
      float lead_side = 0.0f;
      for (size_t i = 0; i < tags.size(); ++i) {
        if (!tags[i].pattern_fitted) continue;
        const float side = internal::MeanSide(tags[i].corners);
        if (side > lead_side) {
          lead_side = side;
          frame_blur = checked[i].blur;
        }
      }
      int lead = -1;
      for (int k = static_cast<int>(small.size()) - 1; k >= 0 && lead < 0 && frame_blur < 0.0f; --k) {
        if (!carried(small[k].second)) lead = k;
      }
      if (lead >= 0 && fit(static_cast<size_t>(lead))) frame_blur = fits[small[lead].second].blur;
      internal::ParallelFor(cv::Range(0, static_cast<int>(small.size())), config.threads, [&](const cv::Range& range) {
        for (int k = range.start; k < range.end; ++k) {
          if (k != lead) fit(static_cast<size_t>(k));
        }
      });
    }
    if (fast && config.tracking) internal::UpdateTracked(detector.tracking_.get(), tags, anchored, fits);
    return tags;
  } catch (const cv::Exception& e) {
    throw Error(std::string("Detect: OpenCV cannot run this configuration on a ") + std::to_string(frame.cols) + "x" +
                std::to_string(frame.rows) + " frame: " + e.what());
  }
}

}  // namespace arucotag

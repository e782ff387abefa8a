// bench_detect: times and scores detectors on the same frames in one run, each frame going through
// every detector in turn, and writes JSON for bench/report.py (which adds the nodelet's row from
// bench_nodelet). The reference is OpenCV's own detector with its defaults; every ratio is a
// detector's time over that one's.
//   opencv        cv::aruco::detectMarkers, OpenCV's default parameters (the reference)
//   opencv_subpix the same with CORNER_REFINE_SUBPIX (ours_subpix's reference for accuracy)
//   opencv_aruco3 the same with useAruco3Detection (OpenCV >= 4.6 only)
//   apriltag_d1   AprilTag 3 (libapriltag), tag36h11, quad_decimate 1, 1 thread: tag36h11 sets only
//   apriltag_d2   the same at quad_decimate 2
//   ours          arucotag::Detect, default DetectorConfig, every frame cold (no tracking state)
//   ours_fast     Detect without the whole-pattern fit (pattern_fit_max_side 0), cold
//   ours_video    Detect with the tracking state carried frame to frame: sequences only
//   ours_subpix   Detect with corner_refinement subpix (the refinement options' accuracy)
//   ours_none, ours_contour, ours_apriltag, opencv_contour, opencv_apriltag
//                 the other refinement options, ours and cv::aruco's with the same option (opencv is
//                 cv::aruco's "none"): scored, and timed, in the first pass only (accuracy rows)
//   pipeline      PreprocessFrame (from BGR) + Detect + EstimatePoseFromPNP per tag, as the nodelet
//                 runs it (tracked on sequences)
//
//   bench_detect --data test/data --cache DIR --json FILE [--frames 6] [--sequence-frames 100]
//                [--reps 5] [--threads N] [--all-cores-reps N] [--sets 'a|b'] [--methods a,b]
//                [--misses FILE]
//
// --misses FILE writes one CSV row per expected marker with exact corners (rendered sets) and per
// detector, from the scored pass: its shortest and longest side (px), whether it was found and, when
// found, its worst corner's error (px), so that recall and accuracy can be broken down by size and
// obliqueness.
// --threads sets OpenCV's threads (bench/run.sh: 1); AprilTag always runs on 1 thread.
// --all-cores-reps N times the OpenCV-threaded detectors N more passes at all hardware threads.
// Methods rotate frame by frame so that load from other processes hits all of them alike.
#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <fstream>
#include <functional>
#include <map>
#include <memory>
#include <string>
#include <thread>
#include <vector>

#include <opencv2/aruco.hpp>
#include <opencv2/core/utility.hpp>

#include <arucotag/arucotag.hpp>

#include "frames.hpp"
#include "stats.hpp"
#include "tool_main.hpp"

#ifdef ARUCOTAG_BENCH_APRILTAG
#include <apriltag.h>
#include <tag36h11.h>
#endif

// DetectorParameters::useAruco3Detection came with opencv_contrib 4.6.0.
#if CV_VERSION_MAJOR > 4 || (CV_VERSION_MAJOR == 4 && CV_VERSION_MINOR >= 6)
#define ARUCOTAG_BENCH_ARUCO3 1
#endif

namespace arucotag::bench {
namespace {

double WallMs() {
  return std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now().time_since_epoch()).count();
}

struct Detections {
  std::vector<int> ids;
  std::vector<std::array<cv::Point2f, 4>> corners;
};

Detections FromTags(const std::vector<ArucoTag>& tags) {
  Detections d;
  for (const auto& t : tags) {
    d.ids.push_back(t.id);
    d.corners.push_back(t.corners);
  }
  return d;
}

Detections OpenCvDetect(const cv::Mat& grey, const cv::Ptr<cv::aruco::Dictionary>& dictionary,
                        const cv::Ptr<cv::aruco::DetectorParameters>& parameters) {
  Detections d;
  std::vector<std::vector<cv::Point2f>> corners;
  cv::aruco::detectMarkers(grey, dictionary, corners, d.ids, parameters);
  for (const auto& q : corners) d.corners.push_back({q[0], q[1], q[2], q[3]});
  return d;
}

#ifdef ARUCOTAG_BENCH_APRILTAG
// AprilTag 3's detector for tag36h11 with its defaults (2 corrected bits, refine_edges, sharpening
// 0.25) but for the decimation, on one thread.
class AprilTag36h11 {
 public:
  explicit AprilTag36h11(float quad_decimate) : family_(tag36h11_create()), detector_(apriltag_detector_create()) {
    apriltag_detector_add_family(detector_, family_);
    detector_->quad_decimate = quad_decimate;
    detector_->nthreads = 1;
  }
  ~AprilTag36h11() {
    apriltag_detector_destroy(detector_);
    tag36h11_destroy(family_);
  }
  AprilTag36h11(const AprilTag36h11&) = delete;
  AprilTag36h11& operator=(const AprilTag36h11&) = delete;

  // AprilTag reads the image without writing it. Its corners run counter-clockwise in the image,
  // cv::aruco's clockwise from the top left: on a tag36h11 marker as cv::aruco draws it (same id),
  // p[1] is cv::aruco's top left, p[0] its top right (checked on the renders, where the truth is
  // exact). AprilTag's pixel centres are at +0.5 (a decimated pixel k maps back to
  // (k - 0.5) * f + 0.5), OpenCV's at integers: its corners there are the truth + 0.5 px.
  Detections Detect(const cv::Mat& grey) const {
    image_u8_t image{grey.cols, grey.rows, static_cast<int32_t>(grey.step), const_cast<uint8_t*>(grey.ptr<uint8_t>())};
    zarray_t* found = apriltag_detector_detect(detector_, &image);
    Detections d;
    for (int i = 0; i < zarray_size(found); ++i) {
      apriltag_detection_t* det = nullptr;
      zarray_get(found, i, &det);
      const auto corner = [&](int k) {
        return cv::Point2f(static_cast<float>(det->p[k][0] - 0.5), static_cast<float>(det->p[k][1] - 0.5));
      };
      d.ids.push_back(det->id);
      d.corners.push_back({corner(1), corner(0), corner(3), corner(2)});
    }
    apriltag_detections_destroy(found);
    return d;
  }

 private:
  apriltag_family_t* family_;
  apriltag_detector_t* detector_;
};
#endif

// One detector under test.
struct Method {
  std::string key, label;
  std::function<Detections(const Frame&)> detect;
  std::function<void()> reset = [] {};  // forget state carried between frames
  bool carries_state = false;           // on a sequence: reset once per pass, not before every frame
  bool opencv_threaded = true;          // timed again in the all-cores passes
  bool accuracy_only = false;           // run in the scored pass only (a refinement option's accuracy)
};

// Each of ours's corner refinement options and cv::aruco's with the same option: the pairs whose
// corner errors the report holds against each other, on the markers both found.
struct RefinementPair {
  const char *option, *ours, *opencv;
};
const RefinementPair kRefinementPairs[] = {
    {"none", "ours_none", "opencv"},
    {"subpix", "ours_subpix", "opencv_subpix"},
    {"contour", "ours_contour", "opencv_contour"},
    {"apriltag", "ours_apriltag", "opencv_apriltag"},
};

struct Stats {
  std::string label;
  std::vector<double> wall, cpu, wall_all_cores;
  int found = 0, expected = 0, false_positives = 0;
  std::vector<double> corner_errors;  // px, found markers with known corners
  bool one_pass = false;              // an accuracy row: timed in the scored pass only
  // The same per marker, keyed by (frame, index of the truth in the frame): pairs of detectors are
  // compared on the markers both found.
  std::map<std::pair<int, int>, std::array<double, 4>> marker_errors;
};

// Corner errors of the found markers (truth with corners only), for the accuracy columns.
void CornerErrors(int frame_index, const Frame& frame, const Detections& d, Stats& stats) {
  for (size_t k = 0; k < frame.truth.size(); ++k) {
    const Truth& t = frame.truth[k];
    if (!t.has_corners) continue;
    for (size_t i = 0; i < d.ids.size(); ++i) {
      if (d.ids[i] != t.id) continue;
      const Score s = ScoreFrame(Frame{frame.name, {}, {}, {t}, {}}, {d.ids[i]}, {d.corners[i]});
      if (s.found == 0) continue;
      std::array<double, 4>& errors = stats.marker_errors[{frame_index, static_cast<int>(k)}];
      for (int c = 0; c < 4; ++c) {
        errors[c] = cv::norm(d.corners[i][c] - t.corners[c]);
        stats.corner_errors.push_back(errors[c]);
      }
      break;
    }
  }
}

// Two detectors' corner errors on the markers both found.
struct PairedErrors {
  int markers = 0;
  std::vector<double> first, second;
};

PairedErrors Paired(const Stats& a, const Stats& b) {
  PairedErrors p;
  for (const auto& [key, errors] : a.marker_errors) {
    const auto other = b.marker_errors.find(key);
    if (other == b.marker_errors.end()) continue;
    ++p.markers;
    p.first.insert(p.first.end(), errors.begin(), errors.end());
    p.second.insert(p.second.end(), other->second.begin(), other->second.end());
  }
  return p;
}

// One expected marker as one detector saw it (--misses).
struct MarkerOutcome {
  std::string method;
  int frame = 0, id = -1;
  double min_side = 0.0, max_side = 0.0;  // px
  bool found = false;
  double worst_corner_error = -1.0;  // px, of a found marker; < 0: not found
};

struct SetResult {
  std::string name, size, dictionary;
  std::vector<MarkerOutcome> outcomes;  // --misses
  int frames = 0;
  bool sequence = false, exact_corners = false;
  std::vector<std::string> order;       // method keys as run
  std::map<std::string, Stats> methods;
  double max_diff_to_full_px = 0.0;     // ours against the full search (fast_path off), same ids
  int ids_differing = 0;                // markers one of them reports and the other not
  unsigned long long full_searches = 0, tracked_frames = 0;  // ours_video
  unsigned long long read_at_prediction = 0, searched_pixels = 0;  // ours_video
  int worst_new_marker_delay = -1;      // frames, ours_video on the sequence
  double mean_new_marker_delay = 0.0;
  double pose_us_total = 0.0;
  long poses = 0;
  std::vector<double> pose_us;  // per tag
  double edge_us_total = 0.0;  // RefineCornersOnEdges alone, on ours's tags
  long edges = 0;
  double pattern_us_total = 0.0;  // RefineCornersOnPattern alone, on ours's tags it applies to
  long patterns = 0;
};

// The full search (cv::aruco with our configuration) next to ours: ids and corners must agree.
void CompareToFull(const Frame& frame, const Detections& fast, const Detector& full, SetResult& r) {
  const Detections ref = FromTags(Detect(frame.grey, full));
  std::vector<bool> used(fast.ids.size(), false);
  for (size_t i = 0; i < ref.ids.size(); ++i) {
    bool matched = false;
    for (size_t j = 0; j < fast.ids.size(); ++j) {
      if (used[j] || fast.ids[j] != ref.ids[i]) continue;
      double d = 0.0;
      for (int c = 0; c < 4; ++c) d = std::max(d, double(cv::norm(fast.corners[j][c] - ref.corners[i][c])));
      if (d > 3.0) continue;
      used[j] = matched = true;
      r.max_diff_to_full_px = std::max(r.max_diff_to_full_px, d);
      break;
    }
    r.ids_differing += !matched;
  }
  for (bool u : used) r.ids_differing += !u;
}

// The edge fit and the pattern fit alone on ours's markers: what they cost per marker.
void TimeRefinement(const Frame& frame, const Detections& d, const DetectorConfig& config,
                    const cv::aruco::Dictionary& dictionary, SetResult& r) {
  if (config.corner_refinement != CornerRefinement::kEdge) return;
  const int cells = dictionary.markerSize + 2 * config.marker_border_bits;
  for (size_t t = 0; t < d.corners.size(); ++t) {
    auto corners = d.corners[t];
    const double e0 = WallMs();
    RefineCornersOnEdges(frame.grey, corners, cells);
    r.edge_us_total += (WallMs() - e0) * 1e3;
    ++r.edges;
    double perimeter = 0.0;
    for (int i = 0; i < 4; ++i) perimeter += cv::norm(corners[i] - corners[(i + 1) % 4]);
    // What one fit costs: the per-frame cap and the sharp markers past pattern_fit_sharp_max_side aside.
    if (perimeter >= 4.0 * config.pattern_fit_max_side) continue;
    const cv::Mat black = MarkerCells(dictionary, d.ids[t], config.marker_border_bits);
    const double p0 = WallMs();
    RefineCornersOnPattern(frame.grey, black, corners);
    r.pattern_us_total += (WallMs() - p0) * 1e3;
    ++r.patterns;
  }
}

// Every detector that applies to `set`, the reference first. Detectors live as long as the set runs.
struct Lineup {
  std::vector<Method> methods;
  DetectorConfig config;
  std::shared_ptr<Detector> full;   // fast_path off: the full search ours is checked against
  std::shared_ptr<Detector> video;  // ours_video's, for its tracking statistics
  std::shared_ptr<std::vector<double>> pose_us;  // the pipeline's PnP times (us) in its last call
};

bool Wanted(const std::vector<std::string>& keys, const std::string& key) {
  return keys.empty() || std::find(keys.begin(), keys.end(), key) != keys.end();
}

Lineup MakeLineup(const FrameSet& set, const std::vector<std::string>& wanted) {
  Lineup l;
  const auto dictionary = cv::aruco::getPredefinedDictionary(DictionaryFromName(set.dictionary));
  const auto opencv_defaults = cv::aruco::DetectorParameters::create();
  l.methods.push_back({"opencv", "OpenCV detectMarkers, defaults",
                       [=](const Frame& f) { return OpenCvDetect(f.grey, dictionary, opencv_defaults); }});
  // The same with OpenCV's sub-pixel corner refinement, to hold ours_subpix against.
  const auto opencv_subpix = cv::aruco::DetectorParameters::create();
  opencv_subpix->cornerRefinementMethod = cv::aruco::CORNER_REFINE_SUBPIX;
  l.methods.push_back({"opencv_subpix", "OpenCV detectMarkers, subpix refinement",
                       [=](const Frame& f) { return OpenCvDetect(f.grey, dictionary, opencv_subpix); }});
#ifdef ARUCOTAG_BENCH_ARUCO3
  const auto aruco3 = cv::aruco::DetectorParameters::create();
  aruco3->useAruco3Detection = true;
  l.methods.push_back({"opencv_aruco3", "OpenCV detectMarkers, ArUco3 mode",
                       [=](const Frame& f) { return OpenCvDetect(f.grey, dictionary, aruco3); }});
#endif
#ifdef ARUCOTAG_BENCH_APRILTAG
  if (set.dictionary == "DICT_APRILTAG_36h11") {
    for (int decimate : {1, 2}) {
      auto apriltag = std::make_shared<AprilTag36h11>(static_cast<float>(decimate));
      Method m{"apriltag_d" + std::to_string(decimate),
               "AprilTag 3 tag36h11, decimate " + std::to_string(decimate) + ", 1 thread",
               [apriltag](const Frame& f) { return apriltag->Detect(f.grey); }};
      m.opencv_threaded = false;
      l.methods.push_back(m);
    }
  }
#endif
  l.config.dictionary = set.dictionary;
  l.config.default_side_length = set.side_length;
  const auto add_ours = [&](const std::string& key, const std::string& label, const DetectorConfig& config,
                            bool carries_state) {
    auto detector = std::make_shared<Detector>(config);
    Method m{key, label, [detector](const Frame& f) { return FromTags(Detect(f.grey, *detector)); },
             [detector] { detector->ResetTracking(); }, carries_state};
    l.methods.push_back(m);
    return detector;
  };
  add_ours("ours", "ours, default config", l.config, false);
  DetectorConfig fast = l.config;
  fast.pattern_fit_max_side = 0;
  add_ours("ours_fast", "ours, fast (no pattern fit)", fast, false);
  if (set.sequence) l.video = add_ours("ours_video", "ours, video mode (tracking)", l.config, true);
  DetectorConfig subpix = l.config;
  subpix.corner_refinement = CornerRefinement::kSubpix;
  add_ours("ours_subpix", "ours, subpix refinement", subpix, false);
  // The other refinement options, ours against cv::aruco's with the same option (its "none" is the
  // reference itself), for their accuracy: one pass.
  const struct {
    const char* name;
    CornerRefinement ours;
    int opencv;
  } options[] = {{"none", CornerRefinement::kNone, -1},
                 {"contour", CornerRefinement::kContour, cv::aruco::CORNER_REFINE_CONTOUR},
                 {"apriltag", CornerRefinement::kApriltag, cv::aruco::CORNER_REFINE_APRILTAG}};
  for (const auto& option : options) {
    if (option.opencv >= 0) {
      auto parameters = cv::aruco::DetectorParameters::create();
      parameters->cornerRefinementMethod = option.opencv;
      Method m{std::string("opencv_") + option.name, std::string("OpenCV detectMarkers, ") + option.name + " refinement",
               [=](const Frame& f) { return OpenCvDetect(f.grey, dictionary, parameters); }};
      m.accuracy_only = true;
      l.methods.push_back(m);
    }
    DetectorConfig config = l.config;
    config.corner_refinement = option.ours;
    add_ours(std::string("ours_") + option.name, std::string("ours, ") + option.name + " refinement", config, false);
    l.methods.back().accuracy_only = true;
  }

  auto pipeline = std::make_shared<Detector>(l.config);
  const CameraModel camera = set.camera;
  l.pose_us = std::make_shared<std::vector<double>>();
  Method p{"pipeline", "pipeline: preprocess + Detect + PnP",
           [pipeline, camera, pose_us = l.pose_us](const Frame& f) {
             pose_us->clear();
             cv::Mat grey;
             PreprocessFrame(f.bgr, grey);
             std::vector<ArucoTag> tags = Detect(grey, *pipeline, camera);  // as the nodelet: through the lens
             for (auto& tag : tags) {
               const double p0 = WallMs();
               EstimatePoseFromPNP(camera, tag);
               pose_us->push_back((WallMs() - p0) * 1e3);
             }
             return FromTags(tags);
           },
           [pipeline] { pipeline->ResetTracking(); }, true};
  l.methods.push_back(p);
  // --methods: the reference always stays, every ratio is to it.
  l.methods.erase(std::remove_if(l.methods.begin() + 1, l.methods.end(),
                                 [&](const Method& m) { return !Wanted(wanted, m.key); }),
                  l.methods.end());
  if (l.video && !Wanted(wanted, "ours_video")) l.video.reset();

  DetectorConfig full_config = l.config;
  full_config.fast_path = false;
  l.full = std::make_shared<Detector>(full_config);
  return l;
}

// `reps` passes over the set, every method on every frame, rotating which goes first. The first
// pass of the 1-thread run is also the one scored.
void Pass(const FrameSet& set, Lineup& l, int reps, bool all_cores, SetResult& r) {
  std::vector<Method*> methods;
  for (auto& m : l.methods) {
    if (!all_cores || m.opencv_threaded) methods.push_back(&m);
  }
  std::map<int, int> first_truth, first_found;  // sequence: id -> frame (ours_video)
  for (int rep = 0; rep < reps; ++rep) {
    const bool score = !all_cores && rep == 0;
    for (Method* m : methods) m->reset();
    for (size_t k = 0; k < set.frames.size(); ++k) {
      const Frame& frame = set.frames[k];
      for (size_t i = 0; i < methods.size(); ++i) {
        Method& m = *methods[(i + k + rep) % methods.size()];
        if (m.accuracy_only && !score) continue;
        if (!(set.sequence && m.carries_state)) m.reset();
        const double w0 = WallMs(), c0 = CpuMs();
        const Detections d = m.detect(frame);
        const double wall = WallMs() - w0, cpu = CpuMs() - c0;
        Stats& s = r.methods[m.key];
        if (all_cores) {
          s.wall_all_cores.push_back(wall);
          continue;
        }
        s.wall.push_back(wall);
        s.cpu.push_back(cpu);
        if (m.key == "pipeline") {
          for (double us : *l.pose_us) r.pose_us_total += us;
          r.poses += static_cast<long>(l.pose_us->size());
          if (score) r.pose_us.insert(r.pose_us.end(), l.pose_us->begin(), l.pose_us->end());
        }
        if (!score) continue;
        const Score sc = ScoreFrame(frame, d.ids, d.corners);
        s.found += sc.found;
        s.expected += sc.expected;
        s.false_positives += sc.false_positives;
        CornerErrors(static_cast<int>(k), frame, d, s);
        for (const Truth& t : frame.truth) {
          if (!t.has_corners) continue;
          MarkerOutcome o{m.key, static_cast<int>(k), t.id, 1e9, 0.0,
                          ScoreFrame(Frame{frame.name, {}, {}, {t}, {}}, d.ids, d.corners).found > 0};
          for (int c = 0; c < 4; ++c) {
            const double side = cv::norm(t.corners[c] - t.corners[(c + 1) % 4]);
            o.min_side = std::min(o.min_side, side);
            o.max_side = std::max(o.max_side, side);
          }
          const auto errors = s.marker_errors.find({static_cast<int>(k), static_cast<int>(&t - frame.truth.data())});
          if (errors != s.marker_errors.end()) {
            o.worst_corner_error = *std::max_element(errors->second.begin(), errors->second.end());
          }
          r.outcomes.push_back(o);
        }
        if (m.key == "ours") {
          if (!set.sequence) CompareToFull(frame, d, *l.full, r);
          TimeRefinement(frame, d, l.config, *l.full->dictionary(), r);
        }
        if (m.key == "ours_video") {
          for (const Truth& t : frame.truth) {
            first_truth.emplace(t.id, static_cast<int>(k));
            const Score one = ScoreFrame(Frame{frame.name, {}, {}, {t}, {}}, d.ids, d.corners);
            if (one.found) first_found.emplace(t.id, static_cast<int>(k));
          }
        }
      }
    }
    if (score && l.video) {
      const auto stats = l.video->tracking_stats();  // this pass's: the detector is fresh
      r.full_searches = stats.full_searches;
      r.tracked_frames = stats.tracked_frames;
      r.read_at_prediction = stats.read_at_prediction;
      r.searched_pixels = stats.searched_pixels;
    }
  }
  if (set.sequence && !all_cores && !first_truth.empty()) {
    // Latency to first detection: frames from a marker's first expected frame to its first find.
    r.worst_new_marker_delay = 0;
    double total = 0.0;
    for (const auto& [id, frame] : first_truth) {
      const auto it = first_found.find(id);
      const int delay = it == first_found.end() ? 1000 : std::max(0, it->second - frame);
      r.worst_new_marker_delay = std::max(r.worst_new_marker_delay, delay);
      total += delay;
    }
    r.mean_new_marker_delay = total / first_truth.size();
  }
}

SetResult RunSet(const FrameSet& set, int reps, int all_cores_reps, int threads,
                 const std::vector<std::string>& methods) {
  SetResult r;
  r.name = set.name;
  r.dictionary = set.dictionary;
  r.frames = static_cast<int>(set.frames.size());
  r.sequence = set.sequence;
  r.exact_corners = set.exact_corners;
  r.size = std::to_string(set.frames[0].grey.cols) + "x" + std::to_string(set.frames[0].grey.rows);
  Lineup lineup = MakeLineup(set, methods);
  for (const auto& m : lineup.methods) {
    r.order.push_back(m.key);
    r.methods[m.key].label = m.label;
    r.methods[m.key].one_pass = m.accuracy_only;
  }
  Pass(set, lineup, reps, false, r);
  if (all_cores_reps > 0) {
    cv::setNumThreads(-1);
    Pass(set, lineup, all_cores_reps, true, r);
    cv::setNumThreads(threads);
  }
  return r;
}

std::string Json(const std::string& s) {
  std::string out = "\"";
  for (char c : s) out += (c == '"' || c == '\\') ? std::string("\\") + c : std::string(1, c);
  return out + "\"";
}

std::string LoadAverage() {
  std::ifstream in("/proc/loadavg");
  double one = NAN;
  in >> one;
  return JsonNumber(one);
}

void WriteJson(const std::vector<SetResult>& results, const std::string& path, int reps, int threads,
               int all_cores_reps, const std::string& load_before, const DetectorConfig& defaults) {
  std::vector<double> pose;
  for (const auto& r : results) pose.insert(pose.end(), r.pose_us.begin(), r.pose_us.end());
  double pose_mean = 0.0;
  for (double p : pose) pose_mean += p / std::max<size_t>(1, pose.size());
  std::ofstream out(path);
  out.precision(6);
  out << "{\n  \"tool\": \"bench_detect\",\n  \"opencv\": " << Json(CV_VERSION)
#ifdef ARUCOTAG_BENCH_APRILTAG
      << ",\n  \"apriltag\": " << Json(ARUCOTAG_BENCH_APRILTAG_VERSION)
#else
      << ",\n  \"apriltag\": null"
#endif
      << ",\n  \"threads\": " << threads << ",\n  \"all_cores_reps\": " << all_cores_reps
      << ",\n  \"hardware_threads\": " << std::thread::hardware_concurrency() << ",\n  \"reps\": " << reps
      << ",\n  \"load_average_before\": " << load_before << ",\n  \"load_average_after\": " << LoadAverage()
      << ",\n  \"full_search_interval\": " << defaults.full_search_interval << ",\n  \"pose_us\": {\"count\": " << pose.size()
      << ", \"median\": " << JsonNumber(Percentile(pose, 0.5)) << ", \"p90\": " << JsonNumber(Percentile(pose, 0.9))
      << ", \"mean\": " << pose_mean << "},\n  \"sets\": [\n";
  for (size_t i = 0; i < results.size(); ++i) {
    const SetResult& r = results[i];
    out << "    {\"name\": " << Json(r.name) << ", \"size\": " << Json(r.size) << ", \"dictionary\": " << Json(r.dictionary)
        << ", \"frames\": " << r.frames << ", \"sequence\": " << (r.sequence ? "true" : "false")
        << ", \"exact_corners\": " << (r.exact_corners ? "true" : "false")
        << ", \"max_diff_to_full_px\": " << r.max_diff_to_full_px << ", \"ids_differing_from_full\": " << r.ids_differing
        << ", \"full_searches\": " << r.full_searches << ", \"tracked_frames\": " << r.tracked_frames
        << ", \"read_at_prediction\": " << r.read_at_prediction << ", \"searched_pixels\": " << r.searched_pixels
        << ", \"worst_new_marker_delay\": " << r.worst_new_marker_delay
        << ", \"mean_new_marker_delay\": " << r.mean_new_marker_delay
        << ", \"pose_us_per_tag\": " << (r.poses ? r.pose_us_total / r.poses : 0.0) << ", \"poses\": " << r.poses
        << ", \"edge_fit_us_per_tag\": " << (r.edges ? r.edge_us_total / r.edges : 0.0) << ", \"edge_fits\": " << r.edges
        << ", \"pattern_fit_us_per_tag\": " << (r.patterns ? r.pattern_us_total / r.patterns : 0.0)
        << ", \"pattern_fits\": " << r.patterns << ",\n     \"order\": [";
    for (size_t k = 0; k < r.order.size(); ++k) out << (k ? ", " : "") << Json(r.order[k]);
    out << "],\n     \"methods\": {";
    for (size_t k = 0; k < r.order.size(); ++k) {
      const Stats& s = r.methods.at(r.order[k]);
      double mean = 0.0;
      for (double w : s.wall) mean += w / s.wall.size();
      out << (k ? ", " : "") << "\n       " << Json(r.order[k]) << ": {\"label\": " << Json(s.label)
          << ", \"median_ms\": " << JsonNumber(Percentile(s.wall, 0.5)) << ", \"p90_ms\": " << JsonNumber(Percentile(s.wall, 0.9))
          << ", \"mean_ms\": " << JsonNumber(mean) << ", \"cpu_median_ms\": " << JsonNumber(Percentile(s.cpu, 0.5))
          << ", \"calls\": " << s.wall.size()
          << ", \"all_cores_median_ms\": " << JsonNumber(Percentile(s.wall_all_cores, 0.5))
          << ", \"found\": " << s.found << ", \"expected\": " << s.expected << ", \"false_positives\": " << s.false_positives
          << ", \"corner_errors\": " << s.corner_errors.size()
          << ", \"corner_error_median_px\": " << JsonNumber(Percentile(s.corner_errors, 0.5))
          << ", \"corner_error_p95_px\": " << JsonNumber(Percentile(s.corner_errors, 0.95))
          << ", \"one_pass\": " << (s.one_pass ? "true" : "false") << "}";
    }
    out << "},\n     \"refinement_pairs\": [";
    bool first_pair = true;
    for (const auto& [option, ours, opencv] : kRefinementPairs) {
      if (!r.methods.count(ours) || !r.methods.count(opencv)) continue;
      const PairedErrors p = Paired(r.methods.at(ours), r.methods.at(opencv));
      out << (first_pair ? "" : ", ") << "\n       {\"option\": " << Json(option) << ", \"ours\": " << Json(ours)
          << ", \"opencv\": " << Json(opencv)
          << ", \"common_markers\": " << p.markers
          << ", \"ours_median_px\": " << JsonNumber(Percentile(p.first, 0.5))
          << ", \"ours_p95_px\": " << JsonNumber(Percentile(p.first, 0.95))
          << ", \"opencv_median_px\": " << JsonNumber(Percentile(p.second, 0.5))
          << ", \"opencv_p95_px\": " << JsonNumber(Percentile(p.second, 0.95)) << "}";
      first_pair = false;
    }
    out << "]}" << (i + 1 < results.size() ? "," : "") << "\n";
  }
  out << "  ]\n}\n";
}

void WriteMisses(const std::vector<SetResult>& results, const std::string& path) {
  std::ofstream out(path);
  out << "set,method,frame,id,min_side_px,max_side_px,found,worst_corner_error_px\n";
  for (const auto& r : results) {
    for (const auto& o : r.outcomes) {
      out << '"' << r.name << "\"," << o.method << ',' << o.frame << ',' << o.id << ',' << o.min_side << ','
          << o.max_side << ',' << (o.found ? 1 : 0) << ',';
      if (o.worst_corner_error >= 0.0) out << o.worst_corner_error;
      out << '\n';
    }
  }
}

int Main(int argc, char** argv) {
  const Options options = ParseOptions(argc, argv, "results.json");
  const std::string load_before = LoadAverage();
  if (options.threads > 0) cv::setNumThreads(options.threads);
  const int threads = cv::getNumThreads();
  std::fprintf(stderr, "bench_detect: loading frame sets (rendered once into %s)...\n", options.cache.c_str());
  const std::vector<FrameSet> sets = AllSets(options);

  std::vector<SetResult> results;
  for (const auto& set : sets) {
    if (!Selected(options.sets, set.name)) continue;
    const double t0 = WallMs();
    const int reps = set.sequence ? std::max(1, options.reps / 2) : options.reps;
    const int all_cores_reps = set.sequence ? std::max(1, options.all_cores_reps / 2) : options.all_cores_reps;
    results.push_back(
        RunSet(set, reps, options.all_cores_reps > 0 ? all_cores_reps : 0, threads, options.methods));
    const auto& r = results.back();
    std::fprintf(stderr, "  %-36s opencv %7.2f  ours %7.2f ms median  (%.1f s)\n", set.name.c_str(),
                 Percentile(r.methods.at("opencv").wall, 0.5),
                 r.methods.count("ours") ? Percentile(r.methods.at("ours").wall, 0.5) : NAN,
                 (WallMs() - t0) / 1e3);
  }
  WriteJson(results, options.json, options.reps, threads, options.all_cores_reps, load_before, DetectorConfig());
  std::fprintf(stderr, "bench_detect: wrote %s\n", options.json.c_str());
  if (!options.misses.empty()) {
    WriteMisses(results, options.misses);
    std::fprintf(stderr, "bench_detect: wrote %s\n", options.misses.c_str());
  }
  return 0;
}

}  // namespace
}  // namespace arucotag::bench

int main(int argc, char** argv) {
  return arucotag::bench::RunTool("bench_detect", arucotag::bench::Main, argc, argv);
}

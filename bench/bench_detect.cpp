// bench_detect: times and scores, on the same frames in one run,
//   (a) cv::aruco::detectMarkers with OpenCV's default parameters,
//   (b) arucotag::Detect with the default DetectorConfig,
//   (c) the whole per-frame pipeline: PreprocessFrame (from BGR) + Detect + EstimatePoseFromPNP per tag,
//   (b2) Detect with corner_refinement subpix instead of the default edge fit (the detector alone),
//   (b3) Detect with the edge fit but no whole-pattern fit (pattern_fit_max_side 0): what the
//        pattern fit of small markers costs,
// and writes JSON for bench/report.py (which adds the nodelet's row from bench_nodelet).
//
//   bench_detect --data test/data --cache DIR --json FILE [--frames 6] [--sequence-frames 100]
//                [--reps 5] [--threads N]
//
// Single-frame sets are timed cold: (b) and (c) forget tracked markers before every frame, as for
// the first frame of a stream. The sequence runs in order with tracking, restarted each repetition.
// Methods alternate frame by frame so that load from other processes hits all of them alike.
#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <ctime>
#include <fstream>
#include <map>
#include <sstream>
#include <string>
#include <thread>
#include <vector>

#include <opencv2/aruco.hpp>
#include <opencv2/core/utility.hpp>

#include <arucotag/arucotag.hpp>

#include "frames.hpp"

namespace arucotag::bench {
namespace {

double WallMs() {
  return std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now().time_since_epoch()).count();
}

double CpuMs() {
  timespec t{};
  clock_gettime(CLOCK_PROCESS_CPUTIME_ID, &t);
  return t.tv_sec * 1e3 + t.tv_nsec * 1e-6;
}

double Percentile(std::vector<double> v, double q) {
  if (v.empty()) return NAN;
  std::sort(v.begin(), v.end());
  const double pos = q * (v.size() - 1);
  const size_t i = static_cast<size_t>(pos);
  const double f = pos - i;
  return i + 1 < v.size() ? v[i] * (1 - f) + v[i + 1] * f : v[i];
}

struct Stats {
  std::vector<double> wall, cpu;
  int found = 0, expected = 0, false_positives = 0;
  std::vector<double> corner_errors;  // px, found markers with known corners
  void Add(const Score& s) {
    found += s.found;
    expected += s.expected;
    false_positives += s.false_positives;
  }
};

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

// Corner errors of the found markers (truth with corners only), for the accuracy column.
void CornerErrors(const Frame& frame, const Detections& d, std::vector<double>& out) {
  for (const Truth& t : frame.truth) {
    if (!t.has_corners) continue;
    for (size_t i = 0; i < d.ids.size(); ++i) {
      if (d.ids[i] != t.id) continue;
      const Score s = ScoreFrame(Frame{frame.name, {}, {}, {t}, {}}, {d.ids[i]}, {d.corners[i]});
      if (s.found == 0) continue;
      for (int c = 0; c < 4; ++c) out.push_back(cv::norm(d.corners[i][c] - t.corners[c]));
      break;
    }
  }
}

struct SetResult {
  std::string name, size;
  int frames = 0;
  bool sequence = false;
  std::map<std::string, Stats> methods;  // "a", "b", "b2", "b3", "c"
  double max_diff_to_full_px = 0.0;     // (b) against the full search (fast_path off), same ids
  int ids_differing = 0;                // markers one of them reports and the other not
  unsigned long long full_searches = 0, tracked_frames = 0;
  int worst_new_marker_delay = -1;      // frames, sequence only
  double pose_us_total = 0.0;
  long poses = 0;
  std::vector<double> pose_us;  // per tag
  double edge_us_total = 0.0;  // RefineCornersOnEdges alone, on (b)'s tags
  long edges = 0;
  double pattern_us_total = 0.0;  // RefineCornersOnPattern alone, on (b)'s tags it applies to
  long patterns = 0;
};

// The full search (cv::aruco with our configuration) next to (b): ids and corners must agree.
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

SetResult RunSet(const FrameSet& set, int reps) {
  SetResult r;
  r.name = set.name;
  r.frames = static_cast<int>(set.frames.size());
  r.sequence = set.sequence;
  r.size = std::to_string(set.frames[0].grey.cols) + "x" + std::to_string(set.frames[0].grey.rows);

  const auto dictionary = cv::aruco::getPredefinedDictionary(DictionaryFromName(set.dictionary));
  const auto opencv_defaults = cv::aruco::DetectorParameters::create();
  DetectorConfig config;
  config.dictionary = set.dictionary;
  config.default_side_length = set.side_length;
  const Detector detect_b(config), detect_c(config);
  DetectorConfig subpix_config = config;
  subpix_config.corner_refinement = CornerRefinement::kSubpix;
  const Detector detect_b2(subpix_config);
  DetectorConfig edge_only_config = config;
  edge_only_config.pattern_fit_max_side = 0;
  const Detector detect_b3(edge_only_config);
  DetectorConfig full_config = config;
  full_config.fast_path = false;
  const Detector full(full_config);

  std::map<int, int> first_truth, first_found;  // sequence: id -> frame
  for (int rep = 0; rep < reps; ++rep) {
    const auto reset = [&] {
      detect_b.ResetTracking();
      detect_b2.ResetTracking();
      detect_b3.ResetTracking();
      detect_c.ResetTracking();
    };
    reset();
    for (size_t k = 0; k < set.frames.size(); ++k) {
      const Frame& frame = set.frames[k];
      if (!set.sequence) reset();
      for (int m = 0; m < 5; ++m) {
        const int method = static_cast<int>((m + k + rep) % 5);
        Detections d;
        double pose_us = 0.0;
        long poses = 0;
        const double w0 = WallMs(), c0 = CpuMs();
        if (method == 0) {
          std::vector<std::vector<cv::Point2f>> corners;
          cv::aruco::detectMarkers(frame.grey, dictionary, corners, d.ids, opencv_defaults);
          for (const auto& q : corners) d.corners.push_back({q[0], q[1], q[2], q[3]});
        } else if (method == 1) {
          d = FromTags(Detect(frame.grey, detect_b));
        } else if (method == 3) {
          d = FromTags(Detect(frame.grey, detect_b2));
        } else if (method == 4) {
          d = FromTags(Detect(frame.grey, detect_b3));
        } else {
          cv::Mat grey;
          PreprocessFrame(frame.bgr, grey);
          std::vector<ArucoTag> tags = Detect(grey, detect_c);
          for (auto& tag : tags) {
            const double p0 = WallMs();
            EstimatePoseFromPNP(set.camera, tag);
            const double us = (WallMs() - p0) * 1e3;
            pose_us += us;
            ++poses;
            if (rep == 0) r.pose_us.push_back(us);
          }
          d = FromTags(tags);
        }
        const double wall = WallMs() - w0, cpu = CpuMs() - c0;
        static const char* const kKeys[] = {"a", "b", "c", "b2", "b3"};
        Stats& s = r.methods[kKeys[method]];
        s.wall.push_back(wall);
        s.cpu.push_back(cpu);
        if (rep != 0) continue;
        s.Add(ScoreFrame(frame, d.ids, d.corners));
        CornerErrors(frame, d, s.corner_errors);
        if (method == 2) {
          r.pose_us_total += pose_us;
          r.poses += poses;
        }
        if (method == 1) {
          if (!set.sequence) CompareToFull(frame, d, full, r);
          if (config.corner_refinement == CornerRefinement::kEdge) {
            const int cells = full.dictionary()->markerSize + 2 * config.marker_border_bits;
            for (size_t t = 0; t < d.corners.size(); ++t) {
              auto corners = d.corners[t];
              const double e0 = WallMs();
              RefineCornersOnEdges(frame.grey, corners, cells);
              r.edge_us_total += (WallMs() - e0) * 1e3;
              ++r.edges;
              double perimeter = 0.0;
              for (int i = 0; i < 4; ++i) perimeter += cv::norm(corners[i] - corners[(i + 1) % 4]);
              if (perimeter >= 4.0 * config.pattern_fit_max_side) continue;  // (the per-frame cap aside)
              const cv::Mat black = MarkerCells(*full.dictionary(), d.ids[t], config.marker_border_bits);
              const double p0 = WallMs();
              RefineCornersOnPattern(frame.grey, black, corners);
              r.pattern_us_total += (WallMs() - p0) * 1e3;
              ++r.patterns;
            }
          }
          for (const Truth& t : frame.truth) {
            first_truth.emplace(t.id, static_cast<int>(k));
            const Score sc = ScoreFrame(Frame{frame.name, {}, {}, {t}, {}}, d.ids, d.corners);
            if (sc.found) first_found.emplace(t.id, static_cast<int>(k));
          }
        }
      }
    }
    if (rep == 0) {
      const auto stats = detect_b.tracking_stats();
      r.full_searches = stats.full_searches;
      r.tracked_frames = stats.tracked_frames;
    }
  }
  if (set.sequence) {
    // Only markers that (a)-style full search can see count: measured against when (b) first found
    // each marker that was expected at some frame.
    r.worst_new_marker_delay = 0;
    for (const auto& [id, frame] : first_truth) {
      const auto it = first_found.find(id);
      const int delay = it == first_found.end() ? 1000 : std::max(0, it->second - frame);
      r.worst_new_marker_delay = std::max(r.worst_new_marker_delay, delay);
    }
  }
  return r;
}

std::string Json(const std::string& s) {
  std::string out = "\"";
  for (char c : s) out += (c == '"' || c == '\\') ? std::string("\\") + c : std::string(1, c);
  return out + "\"";
}

void WriteJson(const std::vector<SetResult>& results, const std::string& path, int reps, int threads,
               const DetectorConfig& defaults) {
  std::vector<double> pose;
  for (const auto& r : results) pose.insert(pose.end(), r.pose_us.begin(), r.pose_us.end());
  double pose_mean = 0.0;
  for (double p : pose) pose_mean += p / std::max<size_t>(1, pose.size());
  std::ofstream out(path);
  out.precision(6);
  out << "{\n  \"tool\": \"bench_detect\",\n  \"opencv\": " << Json(CV_VERSION) << ",\n  \"threads\": " << threads
      << ",\n  \"hardware_threads\": " << std::thread::hardware_concurrency() << ",\n  \"reps\": " << reps
      << ",\n  \"full_search_interval\": " << defaults.full_search_interval << ",\n  \"pose_us\": {\"count\": " << pose.size()
      << ", \"median\": " << Percentile(pose, 0.5) << ", \"p90\": " << Percentile(pose, 0.9) << ", \"mean\": " << pose_mean
      << "},\n  \"sets\": [\n";
  const std::map<std::string, std::string> labels = {
      {"a", "(a) cv::aruco::detectMarkers, OpenCV defaults"},
      {"b", "(b) Detect, default config"},
      {"b2", "(b2) Detect, subpix refinement"},
      {"b3", "(b3) Detect, edge fit only (no pattern fit)"},
      {"c", "(c) preprocess + Detect + PnP"}};
  for (size_t i = 0; i < results.size(); ++i) {
    const SetResult& r = results[i];
    out << "    {\"name\": " << Json(r.name) << ", \"size\": " << Json(r.size) << ", \"frames\": " << r.frames
        << ", \"sequence\": " << (r.sequence ? "true" : "false") << ", \"max_diff_to_full_px\": " << r.max_diff_to_full_px
        << ", \"ids_differing_from_full\": " << r.ids_differing << ", \"full_searches\": " << r.full_searches
        << ", \"tracked_frames\": " << r.tracked_frames << ", \"worst_new_marker_delay\": " << r.worst_new_marker_delay
        << ", \"pose_us_per_tag\": " << (r.poses ? r.pose_us_total / r.poses : 0.0) << ", \"poses\": " << r.poses
        << ", \"edge_fit_us_per_tag\": " << (r.edges ? r.edge_us_total / r.edges : 0.0) << ", \"edge_fits\": " << r.edges
        << ", \"pattern_fit_us_per_tag\": " << (r.patterns ? r.pattern_us_total / r.patterns : 0.0)
        << ", \"pattern_fits\": " << r.patterns
        << ",\n     \"methods\": {";
    int m = 0;
    for (const auto& [key, s] : r.methods) {
      out << (m ? ", " : "") << "\n       " << Json(key) << ": {\"label\": " << Json(labels.at(key))
          << ", \"median_ms\": " << Percentile(s.wall, 0.5) << ", \"p90_ms\": " << Percentile(s.wall, 0.9)
          << ", \"mean_ms\": " << [&] { double t = 0; for (double w : s.wall) t += w; return t / s.wall.size(); }()
          << ", \"cpu_median_ms\": " << Percentile(s.cpu, 0.5) << ", \"calls\": " << s.wall.size()
          << ", \"found\": " << s.found << ", \"expected\": " << s.expected
          << ", \"false_positives\": " << s.false_positives
          << ", \"corner_error_p95_px\": " << (s.corner_errors.empty() ? 0.0 : Percentile(s.corner_errors, 0.95)) << "}";
      ++m;
    }
    out << "}}" << (i + 1 < results.size() ? "," : "") << "\n";
  }
  out << "  ]\n}\n";
}

int Main(int argc, char** argv) {
  const Options options = ParseOptions(argc, argv, "results.json");
  const std::string& cache = options.cache;
  const std::string& json = options.json;
  const int reps = options.reps;
  const int threads = options.threads;
  if (threads > 0) cv::setNumThreads(threads);
  std::fprintf(stderr, "bench_detect: loading frame sets (rendered once into %s)...\n", cache.c_str());
  std::vector<FrameSet> sets = AllSets(options);

  std::vector<SetResult> results;
  for (const auto& set : sets) {
    const double t0 = WallMs();
    results.push_back(RunSet(set, set.sequence ? std::max(1, reps / 2) : reps));
    const auto& r = results.back();
    std::fprintf(stderr, "  %-28s a %7.2f  b %7.2f  c %7.2f ms median  (%.1f s)\n", set.name.c_str(),
                 Percentile(r.methods.at("a").wall, 0.5), Percentile(r.methods.at("b").wall, 0.5),
                 Percentile(r.methods.at("c").wall, 0.5), (WallMs() - t0) / 1e3);
  }
  WriteJson(results, json, reps, cv::getNumThreads(), DetectorConfig());
  std::fprintf(stderr, "bench_detect: wrote %s\n", json.c_str());
  return 0;
}

}  // namespace
}  // namespace arucotag::bench

int main(int argc, char** argv) {
  try {
    return arucotag::bench::Main(argc, argv);
  } catch (const std::exception& e) {
    std::fprintf(stderr, "bench_detect: %s\n", e.what());
    return 1;
  }
}

// Frame sets of the detection benchmark: the real photos with their published answers, the same
// photos warped and composited onto other photos, rendered cluttered scenes at three resolutions and
// four tag counts, two rendered tag36h11 sets (AprilTag runs on them too) and a rendered sequence of a
// camera driving past markers. Rendered sets are written once to a cache folder and read back
// afterwards, so every benchmark run times exactly the same pixels.
#pragma once

#include <array>
#include <string>
#include <vector>

#include <opencv2/core.hpp>

#include <arucotag/pose.hpp>

namespace arucotag::bench {

/// One marker a detector is expected to report.
struct Truth {
  int id = -1;
  bool has_corners = false;             ///< false: the source publishes the id only
  std::array<cv::Point2f, 4> corners{};  ///< TL TR BR BL, px
};

struct Frame {
  std::string name;
  cv::Mat bgr;   ///< as loaded or rendered (8-bit BGR)
  cv::Mat grey;  ///< PreprocessFrame(bgr) with default options, what (a) and (b) receive
  std::vector<Truth> truth;
  /// Ids that are in view but not expected (partly outside the frame, or hidden on purpose): a
  /// detector reporting them is neither rewarded nor counted as a false positive.
  std::vector<int> ignore;
};

struct FrameSet {
  std::string name;
  std::string dictionary;
  double side_length = 0.15;  ///< m, for the pose step
  CameraModel camera;
  bool sequence = false;  ///< frames are consecutive: run them in order, carrying tracking state
  /// Truth corners are exact (rendered): corner errors measure accuracy. False for the photos,
  /// whose corners are the publishers' own detections, hand labels, or those warped.
  bool exact_corners = false;
  std::vector<Frame> frames;
};

/// Command line shared by the benchmark programs.
struct Options {
  std::string data = "test/data";                     ///< --data: the real photos
  std::string cache = "/tmp/arucotag_bench_frames";   ///< --cache: rendered frame sets
  std::string json;                                   ///< --json: results file
  int frames = 6;                                     ///< --frames: rendered scenes per synthetic set
  int sequence_frames = 100;                          ///< --sequence-frames
  int reps = 5;                                       ///< --reps: timed passes
  int threads = -1;                                   ///< --threads: OpenCV threads (-1: OpenCV's choice)
  int all_cores_reps = 0;  ///< --all-cores-reps: extra passes at all cores for the OpenCV-threaded methods
  std::vector<std::string> sets;     ///< --sets 'a|b': only the sets whose name contains one of these
  std::vector<std::string> methods;  ///< --methods a,b: only these method keys (bench_detect; opencv always runs)
  std::string misses;  ///< --misses FILE: bench_detect writes each expected marker's sides and who found it (CSV)
};

/// True when `filters` is empty or `name` contains one of them.
bool Selected(const std::vector<std::string>& filters, const std::string& name);

/// Parses the options above; throws arucotag::Error on an unknown option or a missing value.
Options ParseOptions(int argc, char** argv, const std::string& default_json);

/// The real photos, the warped real photos, then every synthetic set, as both benchmark programs
/// time them.
std::vector<FrameSet> AllSets(const Options& options);

/// Loads the five real photos of test/data (two sets: 640x480 tutorial photos, 1280x960 Raspberry
/// Pi photos). Throws arucotag::Error when a file is missing.
std::vector<FrameSet> RealSets(const std::string& data_dir);

/// Frames the renderer did not make: the Raspberry Pi photos of `sources` (markers with known corners)
/// warped by random homographies (scale, rotation, perspective), relit and composited onto the
/// `backgrounds` photos, blurred and noised, at 1280x720; `frames` of them, the same every run.
/// Truth is the sources' published corners through each homography; the backgrounds' own markers
/// (another dictionary) are not expected, so a detector reporting one scores a false positive.
FrameSet WarpedRealSet(const FrameSet& sources, const std::vector<cv::Mat>& backgrounds, int frames);

/// Rendered sets: {640x480, 1280x720, 1920x1080} x {1, 5, 20, 50} tags of DICT_4X4_50; tag36h11
/// (DICT_APRILTAG_36h11) at 1280x720, 12 tags of 14 px and more; small distant tag36h11 (0.15 m at
/// 2-14 m, 1280x720, more noise and blur); `frames` scenes each; then the tracked sequence
/// (`sequence_frames` frames at 1280x720). Read from `cache_dir` when present and written there
/// otherwise.
std::vector<FrameSet> SyntheticSets(const std::string& cache_dir, int frames, int sequence_frames);

/// The tracked sequence alone, rendered in memory (unit tests use it; the benchmark caches it).
/// Markers enter and leave the field of view as the camera moves; `appear_frame` returns, per
/// marker id, the first frame where it is fully in view.
FrameSet RenderSequence(int frames, std::vector<std::pair<int, int>>* appear_frame = nullptr);

/// Matches detections against a frame's truth: a truth marker counts as found when a detection
/// with its id has its centre within max(3 px, a quarter of the marker's side) of the true centre
/// (the id alone when the truth has no corners). Corner accuracy is measured separately: a
/// detection at the right place with the right id is found, however well its corners are refined.
/// Detections of other ids, or far from the truth, are false positives unless listed in `ignore`.
struct Score {
  int expected = 0, found = 0, false_positives = 0;
};
Score ScoreFrame(const Frame& frame, const std::vector<int>& ids,
                 const std::vector<std::array<cv::Point2f, 4>>& corners);

}  // namespace arucotag::bench

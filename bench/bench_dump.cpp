// bench_dump: what arucotag::Detect reads, marker by marker, for checking that a change to the core
// keeps its results, and for counting its instructions.
//
//   bench_dump --data test/data --cache DIR [--frames 6] [--sequence-frames 100] [--sets 'a|b']
//
// Runs Detect (default DetectorConfig for the set's dictionary and size, tracking reset before every
// frame, one OpenCV thread) once on every frame of the benchmark's frame sets (those --sets selects),
// and prints one line per marker: the set, the frame, the id, whether the pattern fit placed it, and
// its four corners to 1e-4 px. Without --sets it then reads test/data's photos (--data) at 7 scales,
// sharp and blurred, with 6 dictionaries, the same way. Two builds' outputs compared with `cmp` say
// whether the markers and corners stayed the same to the bit. Under callgrind,
// `--toggle-collect='arucotag::Detect(*CameraModel const&)'` counts Detect alone.
#include <cstdio>
#include <string>
#include <vector>

#include <opencv2/core/utility.hpp>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>

#include <arucotag/detector.hpp>

#include "frames.hpp"
#include "tool_main.hpp"

namespace arucotag::bench {
namespace {

void Print(const std::string& where, const std::vector<ArucoTag>& tags) {
  for (const ArucoTag& tag : tags) {
    std::printf("%s id %d pattern %d", where.c_str(), tag.id, tag.pattern_fitted ? 1 : 0);
    for (const cv::Point2f& c : tag.corners) std::printf(" %.4f %.4f", c.x, c.y);
    std::printf("\n");
  }
}

// test/data's photos through Detect at several scales and blurs, with dictionaries that are not
// theirs too (where a change would add a false marker).
void DumpPhotos(const std::string& data) {
  const char* photos[] = {"ubiquity_fiducials/tag_01_d7_14cm.png", "ubiquity_fiducials/tag_245-246_d7_14cm.png",
                          "opencv_tutorial/choriginal.jpg", "opencv_tutorial/chocclusion_original.jpg",
                          "opencv_tutorial/singlemarkersoriginal.jpg", "fuzz/damaged_marker_64x48.png"};
  const char* dictionaries[] = {"DICT_4X4_50",         "DICT_5X5_100",        "DICT_6X6_250",
                                "DICT_ARUCO_ORIGINAL", "DICT_APRILTAG_36h11", "DICT_5X5_1000"};
  for (const char* photo : photos) {
    const cv::Mat image = cv::imread(data + "/" + photo, cv::IMREAD_GRAYSCALE);
    if (image.empty()) throw Error(std::string("cannot read ") + data + "/" + photo);
    for (const double scale : {1.0, 0.8, 0.6, 0.5, 0.4, 0.3, 0.2}) {
      for (const bool blur : {false, true}) {
        cv::Mat grey;
        cv::resize(image, grey, cv::Size(), scale, scale, cv::INTER_AREA);
        if (blur) cv::GaussianBlur(grey, grey, cv::Size(0, 0), 0.8);
        for (const char* dictionary : dictionaries) {
          DetectorConfig config;
          config.dictionary = dictionary;
          char where[256];
          std::snprintf(where, sizeof where, "%s/%.1f/%d/%s", photo, scale, blur ? 1 : 0, dictionary);
          Print(where, Detect(grey, Detector(config)));
        }
      }
    }
  }
}

int Main(int argc, char** argv) {
  const Options options = ParseOptions(argc, argv, "");
  const bool photos = options.sets.empty();
  cv::setNumThreads(1);
  for (const FrameSet& set : AllSets(options)) {
    if (!Selected(options.sets, set.name)) continue;
    DetectorConfig config;
    config.dictionary = set.dictionary;
    config.default_side_length = set.side_length;
    Detector detector(config);
    for (size_t k = 0; k < set.frames.size(); ++k) {
      detector.ResetTracking();
      Print(set.name + "#" + std::to_string(k), Detect(set.frames[k].grey, detector));
    }
  }
  if (photos) DumpPhotos(options.data);
  return 0;
}

}  // namespace
}  // namespace arucotag::bench

int main(int argc, char** argv) {
  return arucotag::bench::RunTool("bench_dump", arucotag::bench::Main, argc, argv);
}

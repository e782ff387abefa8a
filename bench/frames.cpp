#include "frames.hpp"

#include <algorithm>
#include <cmath>
#include <filesystem>
#include <fstream>
#include <map>
#include <sstream>

#include <opencv2/calib3d.hpp>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>

#include <arucotag/aruco_tag.hpp>
#include <arucotag/detector.hpp>
#include <arucotag/preprocess.hpp>
#include <arucotag/sim.hpp>

namespace arucotag::bench {

namespace fs = std::filesystem;

namespace {

// Bump when the scene recipe changes so stale caches are rendered again.
constexpr const char* kCacheVersion = "frames-v4";
constexpr double kHfovDeg = 65.0;
constexpr double kDeg = CV_PI / 180.0;

Frame MakeFrame(const std::string& name, const cv::Mat& bgr) {
  Frame frame;
  frame.name = name;
  frame.bgr = bgr;
  PreprocessFrame(bgr, frame.grey);
  return frame;
}

cv::Mat Load(const std::string& path) {
  cv::Mat image = cv::imread(path, cv::IMREAD_COLOR);
  if (image.empty()) throw Error("benchmark: cannot read " + path);
  return image;
}

Truth WithCorners(int id, std::array<cv::Point2f, 4> corners) {
  Truth t;
  t.id = id;
  t.has_corners = true;
  t.corners = corners;
  return t;
}

Truth IdOnly(int id) {
  Truth t;
  t.id = id;
  return t;
}

CameraModel ReadOpenCvCamera(const std::string& path) {
  cv::FileStorage file(path, cv::FileStorage::READ);
  cv::Mat K, D;
  file["camera_matrix"] >> K;
  file["distortion_coefficients"] >> D;
  if (K.rows != 3 || K.cols != 3) throw Error("benchmark: no camera_matrix in " + path);
  K.convertTo(K, CV_64F);
  std::vector<double> distortion;
  if (!D.empty()) D.reshape(1, 1).convertTo(distortion, CV_64F);
  return CameraModel::FromIntrinsics(cv::Matx33d(K), distortion);
}

CameraModel ToModel(const sim::Camera& camera) { return CameraModel::FromIntrinsics(camera.K, camera.dist); }

// Axis-aligned box of the marker grown by `grow` (a multiple of its side) around its centre.
cv::Rect2f GrownBox(const std::array<cv::Point2f, 4>& quad, float grow) {
  cv::Point2f centre(0, 0);
  for (const auto& p : quad) centre += p * 0.25f;
  std::vector<cv::Point2f> grown;
  for (const auto& p : quad) grown.push_back(centre + (p - centre) * grow);
  return cv::boundingRect(grown);
}

bool Inside(const cv::Rect2f& box, cv::Size size, float margin) {
  return box.x >= margin && box.y >= margin && box.x + box.width <= size.width - margin &&
         box.y + box.height <= size.height - margin;
}

// What a scattered scene holds: which markers, how large or how far, how degraded.
struct ScatterRecipe {
  int dictionary = cv::aruco::DICT_4X4_50;
  int id_count = 50;  ///< ids drawn without repeat from 0..id_count-1
  int count = 1;
  double min_px = 18.0;  ///< side range (px) when no range is set: log-uniform from here to what lets `count` fit
  double min_range_m = 0.0, max_range_m = 0.0;  ///< when max_range_m > 0: depth uniform in it instead
  double max_tilt_deg = 50.0;
  double noise_sigma = 2.0, blur_sigma = 0.5;
  /// Lighting: brightness uniform in [brightness, brightness + brightness_spread], and the contrast
  /// RenderOptions applies around mid-grey before it.
  double brightness = 0.85, brightness_spread = 0.3, contrast = 1.0;
};

// Scene with `recipe.count` 0.15 m markers (each id at most once), sides log-uniform between a small
// marker near the detection limit and one that still lets `count` of them fit (or depths uniform in
// the recipe's range), tilted up to max_tilt_deg, never overlapping (so every one is detectable in
// principle), on textured clutter.
Frame RenderScattered(cv::Size size, const ScatterRecipe& recipe, unsigned seed, const std::string& name) {
  const sim::Camera camera = sim::MakeCamera(size, kHfovDeg);
  const double fx = camera.K(0, 0);
  const int count = recipe.count;
  cv::RNG rng(seed * 7919u + count * 104729u + size.width);
  const double side_m = 0.15;
  const double min_px = recipe.min_px;
  const double max_px = std::max(min_px * 1.5, std::min(0.35 * size.height, std::sqrt(double(size.area()) / count) / 1.7));
  const bool by_range = recipe.max_range_m > 0.0;

  std::vector<sim::Marker> markers;
  std::vector<cv::Rect2f> boxes;
  std::vector<int> ids(recipe.id_count);
  for (int i = 0; i < recipe.id_count; ++i) ids[i] = i;
  for (int i = recipe.id_count - 1; i > 0; --i) std::swap(ids[i], ids[rng.uniform(0, i + 1)]);
  for (int k = 0; k < count; ++k) {
    double side_px = by_range ? fx * side_m / rng.uniform(recipe.min_range_m, recipe.max_range_m)
                              : std::exp(rng.uniform(std::log(min_px), std::log(max_px)));
    bool placed = false;
    for (int attempt = 0; attempt < 400 && !placed; ++attempt) {
      if (!by_range && attempt % 100 == 99) side_px = std::max(min_px, side_px * 0.8);
      const double range = fx * side_m / side_px;
      const double u = rng.uniform(0.0, double(size.width)), v = rng.uniform(0.0, double(size.height));
      const cv::Vec3d ray = camera.K.inv() * cv::Vec3d(u, v, 1.0);
      const double axis = rng.uniform(0.0, 360.0), tilt = rng.uniform(0.0, recipe.max_tilt_deg);
      sim::Marker m = sim::FacingCamera(ids[k], side_m, ray * range, tilt * std::cos(axis * kDeg),
                                        tilt * std::sin(axis * kDeg), rng.uniform(0.0, 360.0));
      const cv::Rect2f box = GrownBox(sim::ProjectCorners(camera, m), 1.6f);
      if (!Inside(box, size, 3.0f)) continue;
      if (std::any_of(boxes.begin(), boxes.end(), [&](const cv::Rect2f& b) { return (b & box).area() > 0; })) continue;
      markers.push_back(m);
      boxes.push_back(box);
      placed = true;
    }
  }
  sim::RenderOptions options;
  options.dictionary = recipe.dictionary;
  options.seed = seed;
  options.noise_sigma = recipe.noise_sigma;
  options.blur_sigma = recipe.blur_sigma;
  options.brightness = recipe.brightness + recipe.brightness_spread * rng.uniform(0.0, 1.0);
  options.contrast = recipe.contrast;
  Frame frame = MakeFrame(name, sim::RenderScene(camera, markers, options));
  for (const auto& m : markers) frame.truth.push_back(WithCorners(m.id, sim::ProjectCorners(camera, m)));
  return frame;
}

struct SequenceMarker {
  int id;
  double side;
  cv::Vec3d position;  // world = camera frame at the start
  double yaw_deg, pitch_deg, roll_deg;
};

// A rover camera (1280x720, 65 degrees) driving 5 m sideways and 1.5 m forward past 12 markers at
// 1.8 to 9 m, panning slowly; markers slide in from the right and leave on the left.
const std::vector<SequenceMarker>& SequenceLayout() {
  static const std::vector<SequenceMarker> layout = {
      {3, 0.15, {-2.6, 0.10, 3.0}, 20, -5, 0},   {7, 0.15, {-1.2, -0.30, 5.5}, -10, 0, 15},
      {11, 0.20, {-0.4, 0.25, 2.4}, 35, 10, -5}, {14, 0.15, {0.6, -0.05, 8.5}, 0, 0, 90},
      {18, 0.15, {1.4, 0.30, 4.0}, -30, 5, 0},   {21, 0.15, {2.3, -0.35, 6.5}, 15, -15, 180},
      {25, 0.20, {3.2, 0.05, 3.3}, -40, 0, 10},  {29, 0.15, {3.9, 0.40, 9.0}, 0, 10, -20},
      {33, 0.15, {4.6, -0.20, 5.0}, 25, 0, 45},  {38, 0.15, {5.3, 0.15, 2.8}, -20, -10, 0},
      {42, 0.15, {6.2, -0.30, 7.0}, 10, 5, 270}, {47, 0.20, {7.0, 0.20, 4.2}, -15, 0, 5},
  };
  return layout;
}

}  // namespace

FrameSet RenderSequence(int frames, std::vector<std::pair<int, int>>* appear_frame) {
  const sim::Camera camera = sim::MakeCamera({1280, 720}, kHfovDeg);
  FrameSet set;
  set.name = "sequence 1280x720";
  set.dictionary = "DICT_4X4_50";
  set.camera = ToModel(camera);
  set.sequence = true;
  set.exact_corners = true;
  std::map<int, int> first_seen;
  for (int k = 0; k < frames; ++k) {
    const double t = frames > 1 ? double(k) / (frames - 1) : 0.0;
    // Camera -> world: position and a slow pan about the vertical axis.
    const cv::Vec3d position(-1.0 + 5.0 * t, 0.02 * std::sin(9.0 * t), 1.5 * t);
    const double pan = (4.0 * std::sin(2 * CV_PI * t)) * kDeg;
    const cv::Matx33d r_wc(std::cos(pan), 0, std::sin(pan), 0, 1, 0, -std::sin(pan), 0, std::cos(pan));
    std::vector<sim::Marker> markers;
    for (const auto& s : SequenceLayout()) {
      const sim::Marker world = sim::FacingCamera(s.id, s.side, s.position, s.yaw_deg, s.pitch_deg, s.roll_deg);
      cv::Matx33d r_wm;
      cv::Rodrigues(world.rvec, r_wm);
      sim::Marker m = world;
      cv::Rodrigues(cv::Matx33d(r_wc.t() * r_wm), m.rvec);
      m.tvec = r_wc.t() * (s.position - position);
      if (m.tvec[2] > 0.3) markers.push_back(m);
    }
    sim::RenderOptions options;
    options.seed = 77;  // the clutter stays put: a static scene behind the markers
    options.noise_sigma = 2.0;
    options.blur_sigma = 0.5;
    options.motion_blur_px = 1.0;
    Frame frame = MakeFrame("sequence/" + std::to_string(k), sim::RenderScene(camera, markers, options));
    for (const auto& m : markers) {
      const auto quad = sim::ProjectCorners(camera, m);
      // Expected once the marker and a quarter of its side around it are in view; partly visible
      // markers at the edges are neither expected nor false positives.
      if (Inside(GrownBox(quad, 1.25f), camera.size, 2.0f)) {
        frame.truth.push_back(WithCorners(m.id, quad));
        first_seen.emplace(m.id, k);
      } else {
        frame.ignore.push_back(m.id);
      }
    }
    set.frames.push_back(std::move(frame));
  }
  if (appear_frame) appear_frame->assign(first_seen.begin(), first_seen.end());
  return set;
}

std::vector<FrameSet> RealSets(const std::string& data_dir) {
  FrameSet tutorial;
  tutorial.name = "real 640x480 (3 photos)";
  tutorial.dictionary = "DICT_6X6_250";
  tutorial.side_length = 0.02;
  tutorial.camera = ReadOpenCvCamera(data_dir + "/opencv_tutorial/tutorial_camera_charuco.yml");
  {
    Frame f = MakeFrame("singlemarkersoriginal", Load(data_dir + "/opencv_tutorial/singlemarkersoriginal.jpg"));
    f.truth = {WithCorners(40, {{{359, 310}, {404, 310}, {410, 350}, {362, 350}}}),
               WithCorners(98, {{{427, 255}, {469, 256}, {477, 289}, {434, 288}}}),
               WithCorners(62, {{{233, 273}, {190, 273}, {196, 241}, {237, 241}}}),
               WithCorners(23, {{{298, 185}, {334, 186}, {335, 212}, {297, 211}}}),
               WithCorners(124, {{{425, 163}, {430, 186}, {394, 186}, {390, 162}}}),
               WithCorners(203, {{{195, 155}, {230, 155}, {227, 178}, {190, 178}}})};
    tutorial.frames.push_back(f);
  }
  {
    Frame f = MakeFrame("choriginal", Load(data_dir + "/opencv_tutorial/choriginal.jpg"));
    for (int id = 0; id <= 16; ++id) f.truth.push_back(IdOnly(id));
    tutorial.frames.push_back(f);
  }
  {
    Frame f = MakeFrame("chocclusion_original", Load(data_dir + "/opencv_tutorial/chocclusion_original.jpg"));
    for (int id : {0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 12, 15}) f.truth.push_back(IdOnly(id));
    tutorial.frames.push_back(f);
  }

  FrameSet fiducials;
  fiducials.name = "real 1280x960 (2 photos)";
  fiducials.dictionary = "DICT_5X5_1000";
  fiducials.side_length = 0.145;
  fiducials.camera = CameraModel::FromIntrinsics(
      cv::Matx33d(1006.126285753055, 0, 655.8639244150409, 0, 1004.015433012594, 490.6140221242933, 0, 0, 1),
      {0.1349735087283542, -0.2335869827451621, 0.0006697030315075139, 0.004846737465872353, 0.0});
  {
    Frame f = MakeFrame("tag_01_d7_14cm", Load(data_dir + "/ubiquity_fiducials/tag_01_d7_14cm.png"));
    f.truth = {WithCorners(1, {{{569.89917f, 201.55890f}, {777.42560f, 206.85025f}, {767.95856f, 415.37830f},
                                {565.75311f, 409.24496f}}})};
    fiducials.frames.push_back(f);
  }
  {
    Frame f = MakeFrame("tag_245-246_d7_14cm", Load(data_dir + "/ubiquity_fiducials/tag_245-246_d7_14cm.png"));
    f.truth = {WithCorners(245, {{{307.68246f, 157.38346f}, {545.10131f, 167.04420f}, {540.11614f, 403.27578f},
                                  {305.64746f, 395.01422f}}}),
               WithCorners(246, {{{671.51892f, 173.46070f}, {900.29650f, 178.44973f}, {895.06933f, 407.39855f},
                                  {666.39910f, 403.12911f}}})};
    fiducials.frames.push_back(f);
  }
  return {tutorial, fiducials};
}

namespace {

void WriteSet(const FrameSet& set, const fs::path& dir) {
  fs::create_directories(dir);
  std::ofstream truth(dir / "truth.txt");
  truth.precision(9);
  for (size_t i = 0; i < set.frames.size(); ++i) {
    const Frame& f = set.frames[i];
    cv::imwrite((dir / (std::to_string(i) + ".png")).string(), f.bgr);
    truth << "frame " << i << ' ' << f.truth.size() << ' ' << f.ignore.size() << '\n';
    for (const auto& t : f.truth) {
      truth << t.id;
      for (const auto& c : t.corners) truth << ' ' << c.x << ' ' << c.y;
      truth << '\n';
    }
    for (int id : f.ignore) truth << id << '\n';
  }
  std::ofstream(dir / "VERSION") << kCacheVersion << '\n';
}

bool ReadSet(FrameSet& set, const fs::path& dir, int frames) {
  std::ifstream version(dir / "VERSION");
  std::string v;
  if (!(version >> v) || v != kCacheVersion) return false;
  std::ifstream truth(dir / "truth.txt");
  for (int i = 0; i < frames; ++i) {
    std::string word;
    int index = 0, n = 0, ignored = 0;
    if (!(truth >> word >> index >> n >> ignored) || word != "frame" || index != i) return false;
    const cv::Mat bgr = cv::imread((dir / (std::to_string(i) + ".png")).string(), cv::IMREAD_COLOR);
    if (bgr.empty()) return false;
    Frame f = MakeFrame(set.name + "/" + std::to_string(i), bgr);
    for (int k = 0; k < n; ++k) {
      Truth t;
      t.has_corners = true;
      truth >> t.id;
      for (auto& c : t.corners) truth >> c.x >> c.y;
      f.truth.push_back(t);
    }
    for (int k = 0; k < ignored; ++k) {
      int id = 0;
      truth >> id;
      f.ignore.push_back(id);
    }
    if (!truth) return false;
    set.frames.push_back(std::move(f));
  }
  return true;
}

}  // namespace

namespace {

// A scattered set: read from `cache_dir`/`dir` when there, else rendered and written there.
FrameSet ScatteredSet(const std::string& cache_dir, const std::string& dir, const std::string& name,
                      const std::string& dictionary, cv::Size size, const ScatterRecipe& recipe, int frames) {
  FrameSet set;
  set.name = name;
  set.dictionary = dictionary;
  set.camera = ToModel(sim::MakeCamera(size, kHfovDeg));
  set.exact_corners = true;
  const fs::path path = fs::path(cache_dir) / (dir + "_" + std::to_string(frames));
  if (!ReadSet(set, path, frames)) {
    set.frames.clear();
    for (int i = 0; i < frames; ++i) {
      set.frames.push_back(RenderScattered(size, recipe, 1000u + i, set.name + "/" + std::to_string(i)));
    }
    WriteSet(set, path);
  }
  return set;
}

}  // namespace

std::vector<FrameSet> SyntheticSets(const std::string& cache_dir, int frames, int sequence_frames) {
  std::vector<FrameSet> sets;
  const std::vector<cv::Size> sizes = {{640, 480}, {1280, 720}, {1920, 1080}};
  for (const cv::Size& size : sizes) {
    for (int count : {1, 5, 20, 50}) {
      std::ostringstream name;
      name << "synthetic " << size.width << "x" << size.height << ", " << count << (count == 1 ? " tag" : " tags");
      ScatterRecipe recipe;
      recipe.count = count;
      sets.push_back(ScatteredSet(cache_dir, std::to_string(size.width) + "x" + std::to_string(size.height) + "_" +
                                                 std::to_string(count),
                                  name.str(), "DICT_4X4_50", size, recipe, frames));
    }
  }
  // tag36h11, which AprilTag reads too: 8x8 black cells (6x6 code) against 6x6 for DICT_4X4_50, so
  // the smallest, 14 px, have 1.75 px cells.
  ScatterRecipe tag36h11;
  tag36h11.dictionary = cv::aruco::DICT_APRILTAG_36h11;
  tag36h11.id_count = 587;
  tag36h11.count = 12;
  tag36h11.min_px = 14.0;
  sets.push_back(ScatteredSet(cache_dir, "1280x720_tag36h11_12", "tag36h11 1280x720, 12 tags", "DICT_APRILTAG_36h11",
                              {1280, 720}, tag36h11, frames));
  // Small and distant, as a rover sees a post before it is close: 0.15 m at 2-14 m is 75 to 11 px.
  ScatterRecipe distant = tag36h11;
  distant.count = 10;
  distant.min_range_m = 2.0;
  distant.max_range_m = 14.0;
  distant.max_tilt_deg = 40.0;
  distant.noise_sigma = 3.0;
  distant.blur_sigma = 0.8;
  sets.push_back(ScatteredSet(cache_dir, "1280x720_tag36h11_distant_10", "tag36h11 distant 1280x720, 10 tags",
                              "DICT_APRILTAG_36h11", {1280, 720}, distant, frames));
  // The same range at dusk or in a post's shadow: a third to a half of the light and 0.6 of the
  // contrast leave 35-60 grey levels between ink and paper (the distant set has 175-235) under the
  // same sensor noise. Small markers' cells then read at a fraction of the contrast the other sets
  // give, which is what a gate on the second look's grey levels must not lose.
  ScatterRecipe dim = distant;
  dim.brightness = 0.3;
  dim.brightness_spread = 0.2;
  dim.contrast = 0.6;
  sets.push_back(ScatteredSet(cache_dir, "1280x720_tag36h11_distant_dim_10", "tag36h11 distant dim 1280x720, 10 tags",
                              "DICT_APRILTAG_36h11", {1280, 720}, dim, frames));

  const fs::path dir = fs::path(cache_dir) / ("sequence_" + std::to_string(sequence_frames));
  FrameSet sequence;
  sequence.name = "sequence 1280x720";
  if (!ReadSet(sequence, dir, sequence_frames)) {
    sequence = RenderSequence(sequence_frames);
    WriteSet(sequence, dir);
  } else {
    const FrameSet meta = RenderSequence(0);
    sequence.dictionary = meta.dictionary;
    sequence.camera = meta.camera;
    sequence.sequence = true;
    sequence.exact_corners = true;
  }
  sets.push_back(std::move(sequence));
  return sets;
}

FrameSet WarpedRealSet(const FrameSet& sources, const std::vector<cv::Mat>& backgrounds, int frames) {
  const cv::Size size(1280, 720);
  FrameSet set;
  set.name = "real warped 1280x720";
  set.dictionary = sources.dictionary;
  set.side_length = sources.side_length;
  set.camera = ToModel(sim::MakeCamera(size, kHfovDeg));  // nominal: each warp is its own camera
  for (int i = 0; i < frames; ++i) {
    cv::RNG rng(4242u + 31u * i);
    // The background photo scaled to cover the frame, centre crop.
    const cv::Mat& background = backgrounds[i % backgrounds.size()];
    const double cover = std::max(double(size.width) / background.cols, double(size.height) / background.rows);
    cv::Mat scaled;
    cv::resize(background, scaled, cv::Size(), cover, cover, cv::INTER_LINEAR);
    cv::Mat canvas;
    scaled(cv::Rect((scaled.cols - size.width) / 2, (scaled.rows - size.height) / 2, size.width, size.height))
        .convertTo(canvas, CV_32FC3);
    Frame frame;
    std::vector<cv::Rect2f> boxes;
    for (const Frame& source : sources.frames) {
      // The region pasted: the markers' bounding box and half a side of the photo around it.
      std::vector<cv::Point2f> points;
      double side = 0.0;
      for (const Truth& t : source.truth) {
        for (int c = 0; c < 4; ++c) {
          points.push_back(t.corners[c]);
          side += cv::norm(t.corners[c] - t.corners[(c + 1) % 4]) / (4.0 * source.truth.size());
        }
      }
      const cv::Rect region = (cv::boundingRect(points) + cv::Size(int(side), int(side)) - cv::Point(int(side / 2), int(side / 2))) &
                              cv::Rect(0, 0, source.bgr.cols, source.bgr.rows);
      const std::vector<cv::Point2f> from = {{0, 0}, {float(region.width), 0}, {float(region.width), float(region.height)},
                                             {0, float(region.height)}};
      for (int attempt = 0; attempt < 200; ++attempt) {
        // Marker sides log-uniform in 16-160 px, any in-plane rotation, corners moved by up to 12% of
        // the region for perspective.
        const double scale = std::exp(rng.uniform(std::log(16.0), std::log(160.0))) / side;
        const double angle = rng.uniform(0.0, 2 * CV_PI);
        const cv::Point2f centre(float(rng.uniform(0.0, double(size.width))), float(rng.uniform(0.0, double(size.height))));
        const float jitter = float(0.12 * scale * std::min(region.width, region.height));
        std::vector<cv::Point2f> to;
        for (const auto& p : from) {
          const cv::Point2f d = (p - cv::Point2f(region.width / 2.f, region.height / 2.f)) * float(scale);
          to.push_back(centre + cv::Point2f(float(d.x * std::cos(angle) - d.y * std::sin(angle)),
                                            float(d.x * std::sin(angle) + d.y * std::cos(angle))) +
                       cv::Point2f(float(rng.uniform(-jitter, jitter)), float(rng.uniform(-jitter, jitter))));
        }
        const cv::Rect2f box = cv::boundingRect(to);
        if (!Inside(box, size, 2.0f)) continue;
        if (std::any_of(boxes.begin(), boxes.end(), [&](const cv::Rect2f& b) { return (b & box).area() > 0; })) continue;
        boxes.push_back(box);
        const cv::Mat h = cv::getPerspectiveTransform(from, to);
        // Low-pass before shrinking so the warp does not alias the cells.
        cv::Mat patch = source.bgr(region).clone();
        if (scale < 0.8) cv::GaussianBlur(patch, patch, cv::Size(), 0.45 / scale);
        cv::Mat warped, alpha;
        cv::warpPerspective(patch, warped, h, size, cv::INTER_LINEAR, cv::BORDER_CONSTANT);
        cv::warpPerspective(cv::Mat(patch.size(), CV_32FC1, cv::Scalar(1.0)), alpha, h, size, cv::INTER_LINEAR,
                            cv::BORDER_CONSTANT, cv::Scalar(0.0));
        warped.convertTo(warped, CV_32FC3, rng.uniform(0.7, 1.15));
        cv::Mat alpha3;
        cv::merge(std::vector<cv::Mat>(3, alpha), alpha3);
        canvas = canvas.mul(cv::Scalar::all(1.0) - alpha3) + warped.mul(alpha3);
        for (const Truth& t : source.truth) {
          std::vector<cv::Point2f> corners(t.corners.begin(), t.corners.end()), moved;
          for (auto& c : corners) c -= cv::Point2f(region.tl());
          cv::perspectiveTransform(corners, moved, h);
          frame.truth.push_back(WithCorners(t.id, {moved[0], moved[1], moved[2], moved[3]}));
        }
        break;
      }
    }
    cv::GaussianBlur(canvas, canvas, cv::Size(), rng.uniform(0.3, 1.2));
    cv::Mat noise(size, CV_32FC3);
    rng.fill(noise, cv::RNG::NORMAL, 0.0, rng.uniform(1.0, 4.0));
    cv::Mat bgr;
    cv::Mat(canvas + noise).convertTo(bgr, CV_8UC3);
    Frame made = MakeFrame(set.name + "/" + std::to_string(i), bgr);
    made.truth = std::move(frame.truth);
    set.frames.push_back(std::move(made));
  }
  return set;
}

Score ScoreFrame(const Frame& frame, const std::vector<int>& ids,
                 const std::vector<std::array<cv::Point2f, 4>>& corners) {
  Score score;
  score.expected = static_cast<int>(frame.truth.size());
  std::vector<bool> used(ids.size(), false);
  for (const Truth& t : frame.truth) {
    for (size_t i = 0; i < ids.size(); ++i) {
      if (used[i] || ids[i] != t.id) continue;
      if (t.has_corners) {
        cv::Point2f truth(0, 0), seen(0, 0);
        double side = 0.0;
        for (int c = 0; c < 4; ++c) {
          truth += t.corners[c] * 0.25f;
          seen += corners[i][c] * 0.25f;
          side += cv::norm(t.corners[c] - t.corners[(c + 1) % 4]) / 4.0;
        }
        if (cv::norm(truth - seen) > std::max(3.0, 0.25 * side)) continue;
      }
      used[i] = true;
      ++score.found;
      break;
    }
  }
  for (size_t i = 0; i < ids.size(); ++i) {
    if (used[i]) continue;
    if (std::find(frame.ignore.begin(), frame.ignore.end(), ids[i]) != frame.ignore.end()) continue;
    ++score.false_positives;
  }
  return score;
}

namespace {

std::vector<std::string> Split(const std::string& list, char separator) {
  std::vector<std::string> items;
  std::stringstream in(list);
  for (std::string item; std::getline(in, item, separator);) {
    if (!item.empty()) items.push_back(item);
  }
  return items;
}

}  // namespace

bool Selected(const std::vector<std::string>& filters, const std::string& name) {
  if (filters.empty()) return true;
  return std::any_of(filters.begin(), filters.end(),
                     [&](const std::string& f) { return name.find(f) != std::string::npos; });
}

Options ParseOptions(int argc, char** argv, const std::string& default_json) {
  Options options;
  options.json = default_json;
  for (int i = 1; i < argc; ++i) {
    const std::string arg = argv[i];
    const auto next = [&]() -> std::string {
      if (i + 1 >= argc) throw Error("missing value after " + arg);
      return argv[++i];
    };
    if (arg == "--data") options.data = next();
    else if (arg == "--cache") options.cache = next();
    else if (arg == "--json") options.json = next();
    else if (arg == "--frames") options.frames = std::stoi(next());
    else if (arg == "--sequence-frames") options.sequence_frames = std::stoi(next());
    else if (arg == "--reps") options.reps = std::stoi(next());
    else if (arg == "--threads") options.threads = std::stoi(next());
    else if (arg == "--all-cores-reps") options.all_cores_reps = std::stoi(next());
    else if (arg == "--sets") options.sets = Split(next(), '|');
    else if (arg == "--methods") options.methods = Split(next(), ',');
    else if (arg == "--misses") options.misses = next();
    else throw Error("unknown option " + arg);
  }
  return options;
}

std::vector<FrameSet> AllSets(const Options& options) {
  std::vector<FrameSet> sets = RealSets(options.data);
  // The Raspberry Pi photos (corners known) onto the tutorial photos (another dictionary).
  std::vector<cv::Mat> backgrounds;
  for (const Frame& f : sets[0].frames) backgrounds.push_back(f.bgr);
  sets.push_back(WarpedRealSet(sets[1], backgrounds, options.frames));
  for (auto& s : SyntheticSets(options.cache, options.frames, options.sequence_frames)) sets.push_back(std::move(s));
  return sets;
}

}  // namespace arucotag::bench

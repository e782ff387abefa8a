// bench_pose: `make bench`'s pose-trust table. Renders --frames (default 1000) random markers, 1-15 m,
// 0-70 degrees off head-on, on a 1280x720 camera with a 65 degree field of view, with pixel noise and
// blur, and an organized cloud with a ZED 2's stereo depth noise (sim::DepthNoise::Zed2(): sigma_z =
// z^2 0.15 px / (f B), correlated in patches, holes, fattened edges). For each detected marker it
// solves PnP, the cloud pose and the fused pose, and reports per range bin: flipped poses (rotation
// error > 10 degrees) for each, the median rotation error, the mean NEES of each one's translation
// and rotation against its own covariance (3 is calibrated; PnP and fused flips left out), and the
// time per tag. --csv writes one row per detected marker (geometry, corner noise, errors, NEES) for
// calibrating the covariances.
//
// A second table compares the cloud's plane fits (CloudPoseOptions::plane_fit) on the same tags:
// per range bin the median normal, rotation and centre errors of the cloud pose, the flips of the
// cloud and fused poses, and the time per tag of the cloud step; --edge-background F first moves
// that fraction of the cloud points each tag's pose uses, the outermost, 1 m further along their
// rays (a wall behind the tag seen past its edge, as stereo matching fattens edges).
// --pattern-fit-max-side N sets the detector's DetectorConfig::pattern_fit_max_side (default: the
// default config's), so the covariances of corners from the edge fit alone (0) can be checked too;
// --pattern-fit-sharp-max-side N its pattern_fit_sharp_max_side.
//
//   bench_pose [--frames 1000] [--json FILE] [--csv FILE] [--seed 7] [--plane-fits ransac,legacy]
//              [--edge-background 0] [--pattern-fit-max-side N] [--pattern-fit-sharp-max-side N]
#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <fstream>
#include <string>
#include <utility>
#include <vector>

#include <opencv2/calib3d.hpp>
#include <opencv2/imgproc.hpp>

#include <arucotag/arucotag.hpp>
#include <arucotag/sim.hpp>

#include "stats.hpp"
#include "tool_main.hpp"

namespace arucotag::bench {
namespace {

using Clock = std::chrono::steady_clock;
constexpr double kFlipDeg = 10.0;
constexpr int kTimingRuns = 3;  // per tag and plane fit in the comparison
const double kBins[] = {1.0, 3.0, 6.0, 10.0, 15.0};
constexpr int kBinCount = 4;
constexpr int kMethods = 3;  // pnp, cloud, fused
const char* const kMethodNames[kMethods] = {"pnp", "cloud", "fused"};

struct FitName {
  const char* name;
  PlaneFit fit;
};
const FitName kFitNames[] = {
    {"ransac", PlaneFit::kRansac}, {"msac", PlaneFit::kMsac}, {"lmeds", PlaneFit::kLmeds}, {"mlesac", PlaneFit::kMlesac},
    {"legacy", PlaneFit::kLegacy}};

std::vector<FitName> ParseFits(const std::string& list) {
  std::vector<FitName> fits;
  size_t start = 0;
  while (start <= list.size()) {
    const size_t end = std::min(list.find(',', start), list.size());
    const std::string name = list.substr(start, end - start);
    const auto known = std::find_if(std::begin(kFitNames), std::end(kFitNames),
                                    [&](const FitName& f) { return name == f.name; });
    if (known == std::end(kFitNames)) throw Error("unknown plane fit '" + name + "' (ransac, msac, lmeds, mlesac, legacy)");
    fits.push_back(*known);
    start = end + 1;
  }
  return fits;
}

// One plane fit's results in one range bin.
struct FitBin {
  int tags = 0, planes = 0, flips_cloud = 0, flips_fused = 0;
  std::vector<double> normal_deg, rotation_deg, centre_mm;
  double ms = 0.0;
};

double RotationDeg(const cv::Vec3d& estimate, const cv::Vec3d& truth) {
  cv::Matx33d a, b;
  cv::Rodrigues(estimate, a);
  cv::Rodrigues(truth, b);
  const double c = std::max(-1.0, std::min(1.0, (cv::trace(a * b.t()) - 1.0) / 2.0));
  return std::acos(c) * 180.0 / CV_PI;
}

// Normalised estimation error squared of a 3-vector error against a 3x3 block of the covariance.
double Nees(const cv::Vec3d& error, const PoseCovariance& covariance, int offset) {
  cv::Matx33d block;
  for (int i = 0; i < 3; ++i)
    for (int j = 0; j < 3; ++j) block(i, j) = covariance(offset + i, offset + j);
  const cv::Matx33d inverse = block.inv(cv::DECOMP_SVD);
  return (error.t() * inverse * error)(0);
}

struct Bin {
  int tags = 0;
  int flips[kMethods] = {0, 0, 0};
  int fused_fixed = 0, fused_broke = 0;  // fused against PnP on the same tag
  std::vector<double> rotation[kMethods];
  std::vector<double> nees_t[kMethods], nees_r[kMethods];
};

double Median(std::vector<double> v) {
  if (v.empty()) return std::nan("");
  std::nth_element(v.begin(), v.begin() + v.size() / 2, v.end());
  return v[v.size() / 2];
}

double Mean(const std::vector<double>& v) {
  double sum = 0.0;
  for (double x : v) sum += x;
  return v.empty() ? std::nan("") : sum / v.size();
}

// Moves `fraction` of the finite cloud points the cloud pose uses (inside the tag shrunk by `shrink`),
// the outermost first (in the marker's own square coordinates), 1 m further along their rays.
void PushEdgeToBackground(const ArucoTag& tag, double fraction, double shrink, cv::Mat& cloud) {
  const std::vector<cv::Point2f> quad(tag.corners.begin(), tag.corners.end());
  const std::vector<cv::Point2f> square{{-0.5f, 0.5f}, {0.5f, 0.5f}, {0.5f, -0.5f}, {-0.5f, -0.5f}};
  const cv::Matx33d to_marker = cv::getPerspectiveTransform(quad, square);
  const cv::Rect box = cv::boundingRect(quad) & cv::Rect(0, 0, cloud.cols, cloud.rows);
  std::vector<std::pair<double, cv::Point>> inside;
  for (int v = box.y; v < box.br().y; ++v) {
    for (int u = box.x; u < box.br().x; ++u) {
      const cv::Vec3d m = to_marker * cv::Vec3d(u, v, 1.0);
      const double edge = std::max(std::abs(m[0] / m[2]), std::abs(m[1] / m[2]));
      if (edge <= 0.5 * (1.0 - shrink) && std::isfinite(cloud.at<cv::Vec3f>(v, u)[2])) inside.push_back({-edge, {u, v}});
    }
  }
  const size_t moved = static_cast<size_t>(fraction * inside.size());
  std::partial_sort(inside.begin(), inside.begin() + moved, inside.end(),
                    [](const auto& a, const auto& b) { return a.first < b.first; });
  for (size_t i = 0; i < moved; ++i) {
    cv::Vec3f& p = cloud.at<cv::Vec3f>(inside[i].second);
    p *= static_cast<float>(1.0 + 1.0 / cv::norm(p));
  }
}

int Main(int argc, char** argv) {
  int frames = 1000;
  unsigned seed = 7;
  std::string json, csv_path;
  std::vector<FitName> fits = ParseFits("ransac,legacy");
  double edge_background = 0.0;
  DetectorConfig config;
  config.default_side_length = 0.15;
  for (int i = 1; i + 1 < argc; i += 2) {
    const std::string arg = argv[i];
    if (arg == "--frames") frames = std::stoi(argv[i + 1]);
    else if (arg == "--json") json = argv[i + 1];
    else if (arg == "--csv") csv_path = argv[i + 1];
    else if (arg == "--seed") seed = static_cast<unsigned>(std::stoul(argv[i + 1]));
    else if (arg == "--plane-fits") fits = ParseFits(argv[i + 1]);
    else if (arg == "--edge-background") edge_background = std::stod(argv[i + 1]);
    else if (arg == "--pattern-fit-max-side") config.pattern_fit_max_side = std::stoi(argv[i + 1]);
    else if (arg == "--pattern-fit-sharp-max-side") config.pattern_fit_sharp_max_side = std::stoi(argv[i + 1]);
    else throw Error("unknown option " + arg);
  }
  const sim::Camera camera = sim::MakeCamera({1280, 720}, 65.0);
  CameraModel model = CameraModel::FromIntrinsics(camera.K, camera.dist);
  model.corner_noise = 0.0;  // lossless renders through their exact intrinsics
  const Detector detector(config);
  CloudPoseOptions cloud_options;
  cloud_options.depth_noise_per_m2 = 0.15 / (camera.K(0, 0) * 0.12);  // the ZED 2 the cloud is made with

  FILE* csv = csv_path.empty() ? nullptr : std::fopen(csv_path.c_str(), "w");
  if (!csv_path.empty() && !csv) throw Error("cannot write " + csv_path);
  if (csv) {
    std::fprintf(csv, "frame,range,obliquity,side_px,min_side_px,min_angle,noise,blur,corner_sigma,rms0,rms1,ambiguity,cloud_points,"
                      "plane_rms,fused,cloud_err_ray,cloud_err_lateral,sol0_rot_deg,sol1_rot_deg,ev_usable,ev_corners,ev_cloud,"
                      "ev_angle0,ev_angle1,ev_normal_sigma");
    for (const char* m : kMethodNames) std::fprintf(csv, ",%s_rot_deg,%s_t_err,%s_nees_t,%s_nees_r", m, m, m, m);
    std::fprintf(csv, ",pattern_fitted\n");
  }
  Bin bins[kBinCount];
  std::vector<std::vector<FitBin>> fit_bins(kBinCount, std::vector<FitBin>(fits.size()));
  double time_ms[kMethods] = {0, 0, 0};
  int timed = 0, missed = 0;
  cv::RNG rng(seed);
  for (int f = 0; f < frames; ++f) {
    const sim::Marker truth = sim::RandomMarker(rng, camera, f % 50, 0.15, kBins[0], kBins[kBinCount], 70.0);
    sim::RenderOptions render;
    render.seed = seed * 100003u + f;
    render.noise_sigma = rng.uniform(0.0, 4.0);
    render.blur_sigma = rng.uniform(0.0, 1.0);
    cv::Mat depth;
    const cv::Mat image = sim::RenderScene(camera, {truth}, render, &depth);
    sim::CloudOptions cloud_render;
    cloud_render.stereo = sim::DepthNoise::Zed2();
    cloud_render.seed = render.seed;
    cv::Mat cloud = sim::MakeOrganizedCloud(camera, depth, cloud_render, image);

    cv::Mat grey;
    PreprocessFrame(image, grey);
    std::vector<ArucoTag> tags = Detect(grey, detector, model);
    const auto found = std::find_if(tags.begin(), tags.end(), [&](const ArucoTag& t) { return t.id == truth.id; });
    if (found == tags.end()) {
      ++missed;
      continue;
    }
    if (edge_background > 0.0) PushEdgeToBackground(*found, edge_background, cloud_options.shrink, cloud);
    ArucoTag pnp = *found;
    auto t0 = Clock::now();
    if (!EstimatePoseFromPNP(model, pnp)) {
      ++missed;
      continue;
    }
    auto t1 = Clock::now();
    ArucoTag cloud_only = *found;
    const bool have_cloud = EstimatePoseFromPointCloud(cloud, camera.size, cloud_only, cloud_options);
    auto t2 = Clock::now();
    ArucoTag fused = pnp;
    if (have_cloud) EstimatePoseFromPointCloud(cloud, camera.size, fused, cloud_options);
    ResolvePose(fused, PoseSource::kFused);
    auto t3 = Clock::now();
    time_ms[0] += std::chrono::duration<double, std::milli>(t1 - t0).count();
    time_ms[1] += std::chrono::duration<double, std::milli>(t2 - t1).count();
    time_ms[2] += std::chrono::duration<double, std::milli>((t1 - t0) + (t3 - t2)).count();
    ++timed;

    const double range = cv::norm(truth.tvec);
    int b = 0;
    while (b + 1 < kBinCount && range > kBins[b + 1]) ++b;
    Bin& bin = bins[b];
    ++bin.tags;
    const ArucoTag* poses[kMethods] = {&pnp, have_cloud ? &cloud_only : nullptr, &fused};
    bool flipped[kMethods] = {false, false, false};
    for (int m = 0; m < kMethods; ++m) {
      if (!poses[m] || !poses[m]->HasPose()) continue;
      const double error = RotationDeg(poses[m]->rvec, truth.rvec);
      bin.rotation[m].push_back(error);
      flipped[m] = error > kFlipDeg;
      bin.flips[m] += flipped[m];
    }
    cv::Matx33d r_truth;
    cv::Rodrigues(truth.rvec, r_truth);
    const cv::Vec3d normal_truth(r_truth(0, 2), r_truth(1, 2), r_truth(2, 2));
    for (size_t k = 0; k < fits.size(); ++k) {
      // Alternate the order, so no fit always finds the cloud in cache.
      const size_t i = f % 2 ? fits.size() - 1 - k : k;
      CloudPoseOptions options = cloud_options;
      options.plane_fit = fits[i].fit;
      FitBin& fb = fit_bins[b][i];
      ArucoTag alone, with_pnp = pnp;
      // The fastest of three runs: other processes on the machine only ever add time.
      bool measured = false;
      double fastest = 1e9;
      for (int run = 0; run < kTimingRuns; ++run) {
        alone = *found;
        const auto start = Clock::now();
        measured = EstimatePoseFromPointCloud(cloud, camera.size, alone, options);
        fastest = std::min(fastest, std::chrono::duration<double, std::milli>(Clock::now() - start).count());
      }
      fb.ms += fastest;
      ++fb.tags;
      if (!measured) continue;
      EstimatePoseFromPointCloud(cloud, camera.size, with_pnp, options);
      ResolvePose(with_pnp, PoseSource::kFused);
      fb.flips_fused += RotationDeg(with_pnp.rvec, truth.rvec) > kFlipDeg;
      fb.centre_mm.push_back(1000.0 * cv::norm(alone.cloud.centre - truth.tvec));
      if (!alone.cloud.has_normal) continue;
      ++fb.planes;
      const double rotation = RotationDeg(alone.rvec, truth.rvec);
      fb.flips_cloud += rotation > kFlipDeg;
      fb.rotation_deg.push_back(rotation);
      fb.normal_deg.push_back(std::acos(std::min(1.0, alone.cloud.normal.dot(normal_truth))) * 180.0 / CV_PI);
    }

    bin.fused_fixed += flipped[0] && !flipped[2];
    bin.fused_broke += !flipped[0] && flipped[2];
    // NEES of each pose against its own covariance. A PnP (or fused) flip is left out: the
    // covariance describes its own solution's neighbourhood, the flip is `ambiguity`'s to report.
    // The cloud has no second solution, so all of its poses count.
    double nees[kMethods][2];
    for (int m = 0; m < kMethods; ++m) {
      nees[m][0] = nees[m][1] = std::nan("");
      if (!poses[m] || !poses[m]->HasPose()) continue;
      const ArucoTag& tag = *poses[m];
      cv::Matx33d r_true, r_est;
      cv::Rodrigues(truth.rvec, r_true);
      cv::Rodrigues(tag.rvec, r_est);
      cv::Vec3d dtheta;
      cv::Rodrigues(r_true * r_est.t(), dtheta);
      nees[m][0] = Nees(truth.tvec - tag.tvec, tag.covariance, 0);
      nees[m][1] = Nees(dtheta, tag.covariance, 3);
      if (m != 1 && flipped[m]) continue;
      bin.nees_t[m].push_back(nees[m][0]);
      if (tag.orientation_measured) bin.nees_r[m].push_back(nees[m][1]);
    }
    if (csv) {
      double side_px = 0.0, min_side_px = 1e9, min_angle = 180.0;
      for (int k = 0; k < 4; ++k) {
        const cv::Point2d a = found->corners[(k + 1) % 4] - found->corners[k];
        const cv::Point2d b = found->corners[(k + 3) % 4] - found->corners[k];
        side_px += 0.25 * cv::norm(a);
        min_side_px = std::min(min_side_px, cv::norm(a));
        min_angle = std::min(min_angle, std::acos(a.dot(b) / (cv::norm(a) * cv::norm(b))) * 180.0 / CV_PI);
      }
      cv::Matx33d r_true;
      cv::Rodrigues(truth.rvec, r_true);
      const double obliquity =
          std::acos(std::abs(cv::Vec3d(r_true(0, 2), r_true(1, 2), r_true(2, 2)).dot(cv::normalize(truth.tvec)))) *
          180.0 / CV_PI;
      std::fprintf(csv, "%d,%.4f,%.2f,%.2f,%.2f,%.2f,%.3f,%.3f,%.5f,%.5f,%.5f,%.4f", f, range, obliquity, side_px,
                   min_side_px, min_angle,
                   render.noise_sigma, render.blur_sigma, pnp.pnp.corner_sigma, pnp.pnp.rms[0], pnp.pnp.rms[1],
                   pnp.pnp.ambiguity);
      const cv::Vec3d ray = cv::normalize(truth.tvec), cloud_error = cloud_only.cloud.centre - truth.tvec;
      std::fprintf(csv, ",%d,%.5f,%d,%.5f,%.5f", cloud_only.cloud.points, cloud_only.cloud.plane_rms,
                   fused.pose_source == PoseSource::kFused, cloud_error.dot(ray),
                   cv::norm(cloud_error - cloud_error.dot(ray) * ray));
      // Both IPPE solutions' rotation errors and what the fused choice weighed, to study its rule.
      const FusedEvidence evidence = WeighFusedEvidence(fused);
      const double sol_rot[2] = {RotationDeg(pnp.pnp.rvec[0], truth.rvec),
                                 pnp.pnp.solutions > 1 ? RotationDeg(pnp.pnp.rvec[1], truth.rvec) : std::nan("")};
      std::fprintf(csv, ",%.4f,%.4f,%d,%.5f,%.5f,%.5f,%.5f,%.5f", sol_rot[0], sol_rot[1], evidence.usable ? 1 : 0,
                   evidence.corners, evidence.cloud, evidence.angle[0], evidence.angle[1], evidence.normal_sigma);
      for (int m = 0; m < kMethods; ++m) {
        const double rot = poses[m] && poses[m]->HasPose() ? RotationDeg(poses[m]->rvec, truth.rvec) : std::nan("");
        const double dt = poses[m] && poses[m]->HasPose() ? cv::norm(poses[m]->tvec - truth.tvec) : std::nan("");
        std::fprintf(csv, ",%.4f,%.5f,%.4f,%.4f", rot, dt, nees[m][0], nees[m][1]);
      }
      std::fprintf(csv, ",%d\n", found->pattern_fitted ? 1 : 0);
    }
  }
  if (csv) std::fclose(csv);

  std::printf("Pose trust: %d rendered frames (1280x720, 65 deg, 0.15 m marker at 1-15 m, 0-70 deg off head-on, "
              "noise 0-4, blur 0-1 px; ZED 2 stereo cloud), %d detected, %d missed.\n\n",
              frames, timed, missed);
  std::printf("| range | tags | flips pnp / cloud / fused | fused fixed / broke | median rot err pnp / cloud / fused "
              "(deg) | NEES t pnp / cloud / fused | NEES r pnp / cloud / fused |\n|---|---|---|---|---|---|---|\n");
  for (int b = 0; b < kBinCount; ++b) {
    const Bin& bin = bins[b];
    std::printf("| %g-%g m | %d | %d / %d / %d | %d / %d | %.2f / %.2f / %.2f | %.2f / %.2f / %.2f | %.2f / %.2f / %.2f |\n",
                kBins[b], kBins[b + 1], bin.tags, bin.flips[0], bin.flips[1], bin.flips[2], bin.fused_fixed,
                bin.fused_broke, Median(bin.rotation[0]), Median(bin.rotation[1]), Median(bin.rotation[2]),
                Mean(bin.nees_t[0]), Mean(bin.nees_t[1]), Mean(bin.nees_t[2]), Mean(bin.nees_r[0]),
                Mean(bin.nees_r[1]), Mean(bin.nees_r[2]));
  }
  std::printf("\nNEES: mean normalised estimation error squared of translation (t) and rotation (r) against the "
              "pose's own covariance; 3 is calibrated, [1.5, 6] the target. PnP and fused flips are left out (the "
              "flip is `ambiguity`'s to report), every cloud pose counts; rotations only where measured.\n");
  std::printf("\nTime per tag: pnp %.3f ms, cloud %.3f ms, fused %.3f ms (pnp + cloud + choice).\n",
              time_ms[0] / std::max(1, timed), time_ms[1] / std::max(1, timed), time_ms[2] / std::max(1, timed));

  std::printf("\nCloud plane fits on the same tags%s: median errors of the cloud pose, flips (> %g deg) of the "
              "cloud and fused poses, time of EstimatePoseFromPointCloud per tag (fastest of %d runs).\n\n",
              edge_background > 0.0 ? (", " + std::to_string(int(100 * edge_background + 0.5)) +
                                        " % of each tag's points moved 1 m behind its edge").c_str()
                                    : "",
              kFlipDeg, kTimingRuns);
  std::printf("| range | fit | tags / planes | normal err (deg) | rot err (deg) | centre err (mm) | flips cloud | "
              "flips fused | ms per tag |\n|---|---|---|---|---|---|---|---|---|\n");
  std::vector<double> fit_ms(fits.size(), 0.0);
  for (int b = 0; b < kBinCount; ++b) {
    for (size_t i = 0; i < fits.size(); ++i) {
      const FitBin& fb = fit_bins[b][i];
      fit_ms[i] += fb.ms;
      std::printf("| %g-%g m | %s | %d / %d | %.2f | %.2f | %.1f | %d | %d | %.3f |\n", kBins[b], kBins[b + 1],
                  fits[i].name, fb.tags, fb.planes, Median(fb.normal_deg), Median(fb.rotation_deg),
                  Median(fb.centre_mm), fb.flips_cloud, fb.flips_fused, fb.ms / std::max(1, fb.tags));
    }
  }
  std::printf("\nCloud step per tag, all bins:");
  for (size_t i = 0; i < fits.size(); ++i) std::printf(" %s %.3f ms", fits[i].name, fit_ms[i] / std::max(1, timed));
  std::printf(".\n");
  if (!json.empty()) {
    std::ofstream out(json);
    out << "{\"frames\": " << frames << ", \"detected\": " << timed << ", \"bins\": [";
    for (int b = 0; b < kBinCount; ++b) {
      const Bin& bin = bins[b];
      out << (b ? ", " : "") << "{\"from_m\": " << kBins[b] << ", \"to_m\": " << kBins[b + 1] << ", \"tags\": " << bin.tags;
      for (int m = 0; m < kMethods; ++m) out << ", \"flips_" << kMethodNames[m] << "\": " << bin.flips[m];
      out << ", \"fused_fixed\": " << bin.fused_fixed << ", \"fused_broke\": " << bin.fused_broke;
      for (int m = 0; m < kMethods; ++m) {
        out << ", \"nees_t_" << kMethodNames[m] << "\": " << JsonNumber(Mean(bin.nees_t[m])) << ", \"nees_r_"
            << kMethodNames[m] << "\": " << JsonNumber(Mean(bin.nees_r[m]));
      }
      out << "}";
    }
    out << "], \"ms_per_tag\": {\"pnp\": " << time_ms[0] / std::max(1, timed) << ", \"cloud\": "
        << time_ms[1] / std::max(1, timed) << ", \"fused\": " << time_ms[2] / std::max(1, timed) << "}";
    out << ", \"edge_background\": " << edge_background << ", \"plane_fits\": {";
    for (size_t i = 0; i < fits.size(); ++i) {
      out << (i ? ", " : "") << "\"" << fits[i].name << "\": {\"ms_per_tag\": " << fit_ms[i] / std::max(1, timed)
          << ", \"bins\": [";
      for (int b = 0; b < kBinCount; ++b) {
        const FitBin& fb = fit_bins[b][i];
        out << (b ? ", " : "") << "{\"tags\": " << fb.tags << ", \"planes\": " << fb.planes
            << ", \"normal_deg\": " << Median(fb.normal_deg) << ", \"rotation_deg\": " << Median(fb.rotation_deg)
            << ", \"centre_mm\": " << Median(fb.centre_mm) << ", \"flips_cloud\": " << fb.flips_cloud
            << ", \"flips_fused\": " << fb.flips_fused << "}";
      }
      out << "]}";
    }
    out << "}}\n";
  }
  return 0;
}

}  // namespace
}  // namespace arucotag::bench

int main(int argc, char** argv) {
  return arucotag::bench::RunTool("bench_pose", arucotag::bench::Main, argc, argv);
}

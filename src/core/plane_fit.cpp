#include "plane_fit.hpp"

#include <algorithm>
#include <cmath>
#include <memory>

#include <pcl/point_cloud.h>
#include <pcl/point_types.h>
#include <pcl/sample_consensus/lmeds.h>
#include <pcl/sample_consensus/mlesac.h>
#include <pcl/sample_consensus/msac.h>
#include <pcl/sample_consensus/ransac.h>
#include <pcl/sample_consensus/sac_model_plane.h>

namespace arucotag::internal {

namespace {

// Inliers lie within this many standard deviations of the camera's depth noise at the tag's range
// from the plane (a point's distance to the plane is at most its error along the ray).
constexpr double kInlierSigmas = 3.0;
// The depth noise is never assumed below this (m): a printed marker is flat to about a millimetre,
// and a camera configured with no noise model (depth_noise 0) still gets a usable threshold.
constexpr double kMinDepthSigma = 0.001;
// Draws at most this many minimal samples. RANSAC and MSAC stop as soon as a sample free of
// outliers has been drawn with 99 % probability (7 draws with 20 % outliers, 35 with half); LMedS
// has no such test and always draws this many.
constexpr int kMaxIterations = 100;
// The consensus runs on at most this many of the samples, evenly spread over the tag: enough to
// tell inliers from outliers at any share of outliers a consensus survives, and the time per tag
// stays that of the least-squares passes over all samples that follow. bench_pose (1000 frames):
// 200 gave the same errors and flips to the digit at 0.039 ms per tag, 22 % over the legacy fit's;
// 100 costs 0.034 against 0.031 ms.
constexpr size_t kConsensusPoints = 100;

// The legacy fit: least squares, drop points whose residual exceeds three robust sigmas of the
// residuals (MAD), three rounds.
bool FitTrimmed(const std::vector<Sample>& samples, const CloudPoseOptions& options, MarkerPlane& plane) {
  plane.use.assign(samples.size(), 1);
  std::vector<double> residuals(samples.size());
  for (int round = 0; round < 3; ++round) {
    if (!FitAffine(samples, plane.use, plane.c, plane.ex, plane.ey)) return false;
    for (size_t i = 0; i < samples.size(); ++i) {
      residuals[i] = cv::norm(samples[i].xyz - (plane.c + samples[i].a * plane.ex + samples[i].b * plane.ey));
    }
    const double threshold = std::max(3.0 * 1.4826 * Median(residuals), 1e-4);
    int kept = 0;
    for (size_t i = 0; i < samples.size(); ++i) {
      plane.use[i] = residuals[i] <= threshold;
      kept += plane.use[i];
    }
    if (kept < options.min_plane_points) return false;
  }
  return true;
}

std::unique_ptr<pcl::SampleConsensus<pcl::PointXYZ>> MakeEstimator(
    PlaneFit method, const pcl::SampleConsensusModelPlane<pcl::PointXYZ>::Ptr& model, double threshold) {
  switch (method) {
    case PlaneFit::kMsac:
      return std::make_unique<pcl::MEstimatorSampleConsensus<pcl::PointXYZ>>(model, threshold);
    case PlaneFit::kLmeds:
      return std::make_unique<pcl::LeastMedianSquares<pcl::PointXYZ>>(model, threshold);
    case PlaneFit::kMlesac:
      return std::make_unique<pcl::MaximumLikelihoodSampleConsensus<pcl::PointXYZ>>(model, threshold);
    default:
      return std::make_unique<pcl::RandomSampleConsensus<pcl::PointXYZ>>(model, threshold);
  }
}

// A consensus fit of the plane with PCL (threshold from the depth-noise model at the tag's median
// depth) on an even subset of the samples, then refined by least squares: the consensus plane
// comes from three points and is only good enough to tell inliers from outliers.
bool FitConsensus(const std::vector<Sample>& samples, const CloudPoseOptions& options, MarkerPlane& plane) {
  const size_t step = (samples.size() + kConsensusPoints - 1) / kConsensusPoints;
  std::vector<double> depth;
  cv::Vec3d origin(0.0, 0.0, 0.0);
  for (size_t i = 0; i < samples.size(); i += step) {
    depth.push_back(samples[i].xyz[2]);
    origin += samples[i].xyz;
  }
  origin *= 1.0 / depth.size();
  double spread = 0.0;
  for (size_t i = 0; i < samples.size(); i += step) spread += cv::norm(samples[i].xyz - origin, cv::NORM_L2SQR);
  spread = std::sqrt(spread / depth.size());
  if (!(spread > 0.0)) return false;
  // PCL works in units of the points' spread about their mean: float keeps its precision 15 m away,
  // and PCL 1.13's test of a degenerate sample (a triangle's doubled area below 1e-5) then means
  // "nearly collinear", not "a few millimetres across" (and logs each one it draws).
  pcl::PointCloud<pcl::PointXYZ>::Ptr cloud(new pcl::PointCloud<pcl::PointXYZ>);
  cloud->reserve(depth.size());
  for (size_t i = 0; i < samples.size(); i += step) {
    const cv::Vec3d p = (samples[i].xyz - origin) / spread;
    cloud->push_back(pcl::PointXYZ(static_cast<float>(p[0]), static_cast<float>(p[1]), static_cast<float>(p[2])));
  }
  const double z = Median(depth);
  const double threshold = kInlierSigmas * std::max(options.depth_noise_per_m2 * z * z, kMinDepthSigma);

  // Not random: the model seeds its sampler with a constant, so a frame always gives one answer.
  pcl::SampleConsensusModelPlane<pcl::PointXYZ>::Ptr model(new pcl::SampleConsensusModelPlane<pcl::PointXYZ>(cloud));
  const auto estimator = MakeEstimator(options.plane_fit, model, threshold / spread);
  estimator->setMaxIterations(kMaxIterations);
  if (!estimator->computeModel()) return false;
  std::vector<int> inliers;
  estimator->getInliers(inliers);
  plane.use.assign(samples.size(), 0);
  for (int i : inliers) plane.use[i * step] = 1;

  // Least squares on the inliers, then the inliers among all samples again by their distance to
  // that plane, twice. The legacy fit's step is kept here: the threshold grows to three robust
  // sigmas (MAD) of the inliers' distances when the points are noisier than the camera's model says
  // (white noise of 1 % of range in PoseCovariance.CloudCentreNees): cut at the model's threshold,
  // their residuals are trimmed and the covariance comes out too small (NEES 6.5, not 3). Over the
  // inliers only, not all points (the legacy fit): a fifth of the points on a wall 1 m behind a tag
  // 6-10 m away would raise the cut over them.
  std::vector<double> distance(samples.size());
  for (int round = 0; round < 3; ++round) {
    // The subset's inliers may be fewer than min_plane_points where all samples' are not.
    if (round > 0 && std::count(plane.use.begin(), plane.use.end(), 1) < options.min_plane_points) return false;
    if (!FitAffine(samples, plane.use, plane.c, plane.ex, plane.ey)) return false;
    if (round == 2) break;
    const cv::Vec3d normal = cv::normalize(plane.ex.cross(plane.ey));
    std::vector<double> inlier_distance;
    for (size_t i = 0; i < samples.size(); ++i) {
      distance[i] = std::abs((samples[i].xyz - plane.c).dot(normal));
      if (plane.use[i]) inlier_distance.push_back(distance[i]);
    }
    const double cut = std::max(threshold, 3.0 * 1.4826 * Median(inlier_distance));
    for (size_t i = 0; i < samples.size(); ++i) plane.use[i] = distance[i] <= cut;
  }
  return true;
}

}  // namespace

bool FitAffine(const std::vector<Sample>& samples, const std::vector<char>& use, cv::Vec3d& c, cv::Vec3d& ex,
               cv::Vec3d& ey) {
  cv::Matx33d ata = cv::Matx33d::zeros();
  cv::Matx33d atb = cv::Matx33d::zeros();  // column j = right-hand side for coordinate j
  for (size_t i = 0; i < samples.size(); ++i) {
    if (!use[i]) continue;
    const cv::Vec3d row(1.0, samples[i].a, samples[i].b);
    ata += row * row.t();
    atb += row * samples[i].xyz.t();
  }
  cv::Matx33d sol;
  if (!cv::solve(ata, atb, sol, cv::DECOMP_CHOLESKY)) return false;
  c = cv::Vec3d(sol(0, 0), sol(0, 1), sol(0, 2));
  ex = cv::Vec3d(sol(1, 0), sol(1, 1), sol(1, 2));
  ey = cv::Vec3d(sol(2, 0), sol(2, 1), sol(2, 2));
  return std::isfinite(cv::norm(c)) && std::isfinite(cv::norm(ex)) && std::isfinite(cv::norm(ey));
}

bool FitMarkerPlane(const std::vector<Sample>& samples, const CloudPoseOptions& options, MarkerPlane& plane) {
  if (static_cast<int>(samples.size()) < options.min_plane_points) return false;
  const bool fitted = options.plane_fit == PlaneFit::kLegacy ? FitTrimmed(samples, options, plane)
                                                             : FitConsensus(samples, options, plane);
  return fitted && cv::norm(plane.ex.cross(plane.ey)) > 0.0 && cv::norm(plane.ex) > 0.0;
}

double Median(std::vector<double> values) {
  const auto mid = values.begin() + values.size() / 2;
  std::nth_element(values.begin(), mid, values.end());
  return *mid;
}

}  // namespace arucotag::internal

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
// 100 costs 0.034 against 0.031 ms (before the consensus tools were kept per thread: 0.030 against
// 0.030 now).
constexpr size_t kConsensusPoints = 100;
// Least-squares refits after the consensus: the first on the subset's inliers, each further one on
// the inliers among all samples. One fewer saved 10 % of the time per tag but, with a fifth of the
// points on a wall 1 m behind the tag (bench_pose --edge-background 0.2, 300 frames), the 3-6 m
// bin's median normal error rose from 16 to 28 degrees.
constexpr int kRefits = 2;

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

// PCL's plane model, restarted for each tag's points: its sampler seeded as PCL seeds it when it
// is made, so a tag always gives one answer whatever this thread fitted before.
class PlaneModel : public pcl::SampleConsensusModelPlane<pcl::PointXYZ> {
 public:
  using SampleConsensusModelPlane::SampleConsensusModelPlane;
  void Restart(const PointCloudConstPtr& cloud) {
    indices_->clear();  // or setInputCloud keeps the previous cloud's indices
    setInputCloud(cloud);
    rng_alg_.seed(12345u);  // PCL's own seed
  }
};

// A PCL estimator that forgets the previous cloud's model: PCL keeps it, and returns it as the
// answer for a cloud none of whose samples gives a model.
template <typename Estimator>
class FreshEstimator : public Estimator {
 public:
  explicit FreshEstimator(const pcl::SampleConsensusModelPlane<pcl::PointXYZ>::Ptr& model) : Estimator(model) {}
  bool computeModel(int debug_verbosity_level = 0) override {
    this->model_.clear();
    return Estimator::computeModel(debug_verbosity_level);
  }
};

// One thread's consensus tools, made on its first tag. Making the model and an estimator for every
// tag seeded four Mersenne twisters and allocated a dozen times: a fit on 100 points (a 0.15 m tag
// at 12 m) took 17 us with them, 10 us without (the legacy fit: 4 us).
struct Consensus {
  pcl::PointCloud<pcl::PointXYZ>::Ptr cloud{new pcl::PointCloud<pcl::PointXYZ>};
  PlaneModel* model = new PlaneModel(cloud);
  // Owns *model, as PCL's own shared pointer: boost's before PCL 1.11 (ROS Noetic's 1.10), std's after.
  pcl::SampleConsensusModelPlane<pcl::PointXYZ>::Ptr model_owner{model};
  std::unique_ptr<pcl::SampleConsensus<pcl::PointXYZ>> estimators[4];

  pcl::SampleConsensus<pcl::PointXYZ>& Estimator(PlaneFit method) {
    const int index = static_cast<int>(method);
    auto& estimator = estimators[index];
    if (!estimator) {
      switch (method) {
        case PlaneFit::kMsac:
          estimator = std::make_unique<FreshEstimator<pcl::MEstimatorSampleConsensus<pcl::PointXYZ>>>(model_owner);
          break;
        case PlaneFit::kLmeds:
          estimator = std::make_unique<FreshEstimator<pcl::LeastMedianSquares<pcl::PointXYZ>>>(model_owner);
          break;
        case PlaneFit::kMlesac:
          estimator =
              std::make_unique<FreshEstimator<pcl::MaximumLikelihoodSampleConsensus<pcl::PointXYZ>>>(model_owner);
          break;
        default:
          estimator = std::make_unique<FreshEstimator<pcl::RandomSampleConsensus<pcl::PointXYZ>>>(model_owner);
      }
      estimator->setMaxIterations(kMaxIterations);
    }
    return *estimator;
  }
};

// A consensus fit of the plane with PCL (threshold from the depth-noise model at the tag's median
// depth) on an even subset of the samples, then refined by least squares: the consensus plane
// comes from three points and is only good enough to tell inliers from outliers.
bool FitConsensus(const std::vector<Sample>& samples, const CloudPoseOptions& options, MarkerPlane& plane) {
  if (samples.size() < 3) return false;  // no plane, and no subset to stride over
  const size_t step = (samples.size() + kConsensusPoints - 1) / kConsensusPoints;
  const size_t count = (samples.size() + step - 1) / step;
  // One pass over the subset: its depths, and its mean and spread about the first point (which
  // keeps the sums of squares small 15 m away).
  std::vector<double> depth(count);
  const cv::Vec3d first = samples[0].xyz;
  cv::Vec3d sum(0.0, 0.0, 0.0);
  double sum_sq = 0.0;
  for (size_t k = 0; k < count; ++k) {
    const cv::Vec3d d = samples[k * step].xyz - first;
    depth[k] = samples[k * step].xyz[2];
    sum += d;
    sum_sq += d.dot(d);
  }
  const cv::Vec3d mean = sum * (1.0 / count);
  const double spread = std::sqrt(std::max(0.0, sum_sq / count - mean.dot(mean)));
  if (!(spread > 0.0)) return false;
  const cv::Vec3d origin = first + mean;
  // PCL works in units of the points' spread about their mean: float keeps its precision 15 m away,
  // and PCL 1.13's test of a degenerate sample (a triangle's doubled area below 1e-5) then means
  // "nearly collinear", not "a few millimetres across" (and logs each one it draws).
  thread_local Consensus consensus;
  pcl::PointCloud<pcl::PointXYZ>& cloud = *consensus.cloud;
  cloud.resize(count);
  for (size_t k = 0; k < count; ++k) {
    const cv::Vec3d p = (samples[k * step].xyz - origin) / spread;
    cloud[k] = pcl::PointXYZ(static_cast<float>(p[0]), static_cast<float>(p[1]), static_cast<float>(p[2]));
  }
  const double z = Median(std::move(depth));
  const double threshold = kInlierSigmas * std::max(options.depth_noise_per_m2 * z * z, kMinDepthSigma);

  consensus.model->Restart(consensus.cloud);
  pcl::SampleConsensus<pcl::PointXYZ>& estimator = consensus.Estimator(options.plane_fit);
  estimator.setDistanceThreshold(threshold / spread);
  if (!estimator.computeModel()) return false;
  std::vector<int> inliers;
  estimator.getInliers(inliers);
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
  std::vector<double> inlier_distance;
  inlier_distance.reserve(samples.size());
  for (int round = 0;; ++round) {
    if (!FitAffine(samples, plane.use, plane.c, plane.ex, plane.ey)) return false;
    if (round == kRefits) return true;
    const cv::Vec3d normal = cv::normalize(plane.ex.cross(plane.ey));
    const double offset = plane.c.dot(normal);
    inlier_distance.clear();
    for (size_t i = 0; i < samples.size(); ++i) {
      distance[i] = std::abs(samples[i].xyz.dot(normal) - offset);
      if (plane.use[i]) inlier_distance.push_back(distance[i]);
    }
    const double cut = std::max(threshold, 3.0 * 1.4826 * Median(inlier_distance));
    int kept = 0;
    for (size_t i = 0; i < samples.size(); ++i) {
      plane.use[i] = distance[i] <= cut;
      kept += plane.use[i];
    }
    // The subset's inliers may be fewer than min_plane_points where all samples' are not.
    if (kept < options.min_plane_points) return false;
  }
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

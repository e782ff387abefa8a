#include <arucotag/pose.hpp>

#include <algorithm>
#include <cmath>
#include <string>

#include <opencv2/calib3d.hpp>
#include <opencv2/imgproc.hpp>

#include "plane_fit.hpp"
#include "reprojection.hpp"

namespace arucotag {

PixelMapping PixelMapping::FromBinningAndRoi(int binning_x, int binning_y, const cv::Point2d& roi_offset) {
  if (binning_x < 1 || binning_y < 1) {
    throw Error("pixel mapping: binning must be at least 1 (got " + std::to_string(binning_x) + "x" +
                std::to_string(binning_y) + ")");
  }
  PixelMapping mapping;
  mapping.scale = cv::Vec2d(binning_x, binning_y);
  // The centre of image pixel 0 is the centre of the binned block's sensor pixels 0 .. b-1.
  mapping.offset = cv::Vec2d(roi_offset.x + 0.5 * (binning_x - 1), roi_offset.y + 0.5 * (binning_y - 1));
  return mapping;
}

cv::Point2d PixelMapping::ToSensor(const cv::Point2d& image) const {
  return {image.x * scale[0] + offset[0], image.y * scale[1] + offset[1]};
}

cv::Point2d PixelMapping::ToImage(const cv::Point2d& sensor) const {
  return {(sensor.x - offset[0]) / scale[0], (sensor.y - offset[1]) / scale[1]};
}

bool PixelMapping::IsIdentity() const { return scale == cv::Vec2d(1.0, 1.0) && offset == cv::Vec2d(0.0, 0.0); }

CameraModel CameraModel::FromIntrinsics(const cv::Matx33d& K, const std::vector<double>& distortion) {
  CameraModel camera;
  camera.K = K;
  camera.distortion = distortion;
  // ROS drivers publish all-zero D for rectified cameras; an empty vector skips OpenCV's undistortion.
  if (std::all_of(distortion.begin(), distortion.end(), [](double d) { return d == 0.0; })) {
    camera.distortion.clear();
  }
  return camera;
}

CameraModel CameraModel::FromFisheye(const cv::Matx33d& K, const std::vector<double>& distortion) {
  CameraModel camera;
  camera.K = K;
  camera.distortion = distortion;  // zeros stay: an equidistant lens without them is still no pinhole
  camera.distortion_model = DistortionModel::kEquidistant;
  return camera;
}

CameraModel CameraModel::FromProjection(const cv::Matx34d& P) {
  CameraModel camera;
  camera.K = P.get_minor<3, 3>(0, 0);
  return camera;
}

void CameraModel::Validate() const {
  const double fx = K(0, 0), fy = K(1, 1), cx = K(0, 2), cy = K(1, 2);
  if (!(std::isfinite(fx) && std::isfinite(fy) && fx > 0.0 && fy > 0.0)) {
    throw Error("camera intrinsics invalid: fx and fy must be positive (got fx=" + std::to_string(fx) +
                ", fy=" + std::to_string(fy) + "); is camera_info calibrated?");
  }
  if (!(std::isfinite(cx) && std::isfinite(cy) && std::isfinite(K(0, 1)))) {
    throw Error("camera intrinsics invalid: cx, cy and the skew must be finite");
  }
  if (K(1, 0) != 0.0 || K(2, 0) != 0.0 || K(2, 1) != 0.0 || K(2, 2) != 1.0) {
    throw Error("camera intrinsics invalid: K must read fx s cx; 0 fy cy; 0 0 1");
  }
  const size_t n = distortion.size();
  if (distortion_model == DistortionModel::kEquidistant) {
    if (n != 4) {
      throw Error("fisheye (equidistant) camera has " + std::to_string(n) + " distortion coefficients; it needs 4 (k1..k4)");
    }
  } else if (n != 0 && n != 4 && n != 5 && n != 8 && n != 12 && n != 14) {
    throw Error("camera distortion has " + std::to_string(n) + " coefficients; OpenCV accepts 4, 5, 8, 12 or 14");
  }
  for (double d : distortion) {
    if (!std::isfinite(d)) throw Error("camera distortion coefficient is not finite");
  }
  const PixelMapping& m = pixels;
  if (!(std::isfinite(m.scale[0]) && std::isfinite(m.scale[1]) && m.scale[0] > 0.0 && m.scale[1] > 0.0 &&
        std::isfinite(m.offset[0]) && std::isfinite(m.offset[1]))) {
    throw Error("camera pixel mapping invalid: scale must be positive and offset finite");
  }
  if (!(std::isfinite(corner_noise) && corner_noise >= 0.0)) {
    throw Error("camera corner_noise invalid: must be a finite number of px >= 0 (got " + std::to_string(corner_noise) +
                ")");
  }
}

std::vector<cv::Point2d> CameraModel::Project(const std::vector<cv::Point3d>& points, const cv::Vec3d& rvec,
                                              const cv::Vec3d& tvec) const {
  std::vector<cv::Point2d> image;
  if (points.empty()) return image;
  if (distortion_model == DistortionModel::kEquidistant) {
    cv::fisheye::projectPoints(points, image, rvec, tvec, K, distortion);
  } else {
    cv::projectPoints(points, rvec, tvec, K, distortion, image);
  }
  if (!pixels.IsIdentity()) {
    for (auto& p : image) p = pixels.ToImage(p);
  }
  return image;
}

std::vector<cv::Point2d> CameraModel::Normalize(const std::vector<cv::Point2d>& image) const {
  std::vector<cv::Point2d> sensor(image), normalized;
  if (image.empty()) return normalized;
  if (!pixels.IsIdentity()) {
    for (auto& p : sensor) p = pixels.ToSensor(p);
  }
  if (distortion_model == DistortionModel::kEquidistant) {
    cv::fisheye::undistortPoints(sensor, normalized, K, distortion);
  } else {
    cv::undistortPoints(sensor, normalized, K, distortion);
  }
  return normalized;
}

namespace {

// A Gauss-Newton step that would remove more than this share of IPPE's squared reprojection error
// means IPPE stopped off a minimum (OpenCV's IPPE degenerates on some exactly frontal views):
// corner noise alone leaves IPPE close to the least-squares minimum whatever its size.
constexpr double kOffMinimumShare = 0.5;
// Below this RMS (px) there is nothing measurable left for another solver to gain.
constexpr double kNegligibleRms = 0.01;
// Two refined solutions whose rotations differ by less than this (rad) are one minimum.
constexpr double kSameMinimumRad = 1e-3;
// Prior on the corner noise (px per coordinate) and the residual degrees of freedom it weighs as:
// the four corners leave only 2 degrees of freedom of residual, too few to trust alone (a 2-dof
// variance estimate is below a tenth of the truth one time in ten), and most of a corner's error
// moves the pose rather than the residual. Measured on 1000 rendered frames (bench_pose: 1-15 m,
// 0-70 degrees, blur 0-1 px, noise 0-4 grey levels): markers of 20-40 px scatter about 0.009 px;
// larger ones more (the edge fit of large blurred edges), growing as side^0.75 above
// kCornerSigmaPriorSide; smaller ones too (12-15 px blurred markers scatter about 0.1 px in the
// worst cases), growing as 1 / side^2 below kCornerSigmaSmallSide. With this prior the mean NEES of
// translation and rotation per range bin (1-3, 3-6, 6-10, 10-15 m) is 3.5/3.1, 1.6/2.6, 3.0/4.0,
// 4.7/4.1 (3 is calibrated; `make bench` prints it), and PoseCovariance.PnpNeesPerRangeBin's (0.2 m
// markers, so 13-20 px at 10-15 m) 3.9/3.0, 1.7/2.6, 1.8/5.6, 1.5/3.1. The small side was 16 px
// until the second chance read more 12-16 px markers (2026-11): those sat at 1.49 in the test's far
// bin, under its 1.5 bound, and bench_pose's far bin at 4.1/3.6 (all with CameraModel::corner_noise 0:
// renders through their exact intrinsics). Real lenses, calibrations, compression and motion blur add
// error these renders do not have, and the 2-dof residual cannot show it: CameraModel::corner_noise
// carries it (on the sample recording the 17-22 px stake's PnP rotations had NEES 100-500 without it).
constexpr double kCornerSigmaPrior = 0.009;
constexpr double kCornerSigmaPriorSide = 40.0;
constexpr double kCornerSigmaPriorGrowth = 0.75;
constexpr double kCornerSigmaSmallSide = 15.0;
constexpr double kCornerSigmaPriorDof = 2.0;
// Corners from the edge fit alone (a marker past pattern_fit_max_side or pattern_fit_max_markers, or
// the pattern fit off or refused): the prior above down to kEdgeCornerSigmaSide, growing as
// side^-1.5 below it. The prior above had been calibrated with every marker under 56 px
// pattern-fitted; put on edge-fitted ones of 15-40 px it read mean NEES 6-60 (bench_pose
// --pattern-fit-max-side 0 --csv, 807 markers: PnP translation / rotation per side of 0-15, 15-20,
// 20-25, 25-30, 30-40, 40-56 px 3.8/2.1, 5.1/4.0, 2.5/2.2, 3.2/2.7, 1.9/3.3, 3.4/3.0 with this one;
// the edge fit's median corner error is about twice the pattern fit's from 30 px up, four times under
// 20 px). Its error is heavy-tailed: the NEES medians are 0.3-1 under 40 px (2.37 for calibrated
// noise), most of the mean coming from blurred (0.7-1 px: mean 4.9 against 0.6 under 0.25 px) and
// oblique markers, which the corners alone do not tell apart.
constexpr double kEdgeCornerSigmaSide = 56.0;
constexpr double kEdgeCornerSigmaGrowth = 1.5;
// A rival planar solution this unlikely (its posterior weight) leaves the pick's covariance as it is.
constexpr double kNegligibleRivalWeight = 1e-6;
// The rival's likelihood is judged under this multiple of the corner noise the covariance assumes
// (PnpResult::corner_sigma). Measured on 2319 rendered markers at 1-15 m (four seeds of
// PoseCovariance.PnpNeesPerRangeBin's scenes, 159 picks of the wrong solution): 1.75-2 predicted
// best how often the pick is wrong; at 1, a third of the wrong picks had a rival weight under 0.1.
// Small near-frontal markers pick the wrong one of two solutions 5-10 degrees apart about one time
// in three at ambiguity 0.2-0.5, and the pick's own neighbourhood put the truth at NEES 100-700.
constexpr double kRivalSigmaScale = 2.0;

using Jacobian = cv::Matx<double, 8, 6>;
using internal::RotationAngle;

// One pose of the marker and what its four corners say about it.
struct Candidate {
  cv::Vec3d rvec, tvec;
  cv::Vec<double, 8> residual;  // projected - found, image px, x and y of TL TR BR BL
  Jacobian jacobian;            // d(projected) / d(tvec, small rotation about the camera axes)
  double SumSq() const { return residual.dot(residual); }
  // Per coordinate, as solvePnPGeneric's own reprojectionError (what this error always was).
  double Rms() const { return std::sqrt(SumSq() / 8.0); }
};

// Projects the corners at (rvec, tvec) through the camera's lens and pixel mapping and fills the
// candidate. Returns false behind the camera or when the error is not finite.
bool Evaluate(const CameraModel& camera, const std::vector<cv::Point3d>& object, const std::vector<cv::Point2d>& image,
              const cv::Vec3d& rvec, const cv::Vec3d& tvec, Candidate& out) {
  if (!(tvec[2] > 0.0)) return false;
  std::vector<cv::Point2d> projected;
  cv::Mat jacobian;
  if (!internal::ProjectWithJacobian(camera, object, rvec, tvec, projected, jacobian)) return false;
  out.rvec = rvec;
  out.tvec = tvec;
  for (size_t k = 0; k < object.size(); ++k) {
    out.residual[2 * k] = projected[k].x - image[k].x;
    out.residual[2 * k + 1] = projected[k].y - image[k].y;
  }
  for (int r = 0; r < Jacobian::rows; ++r) {
    for (int c = 0; c < Jacobian::cols; ++c) out.jacobian(r, c) = jacobian.at<double>(r, c);
  }
  return std::isfinite(out.SumSq());
}

// The share of the squared error one Gauss-Newton step from the candidate would remove: near 0 at
// a least-squares minimum however noisy the corners, near 1 far from one (1 when J is singular).
double OffMinimumShare(const Candidate& c) {
  const cv::Vec6d gradient = c.jacobian.t() * c.residual;
  cv::Vec6d step;
  if (!cv::solve(c.jacobian.t() * c.jacobian, gradient, step, cv::DECOMP_CHOLESKY)) return 1.0;
  const double sum_sq = c.SumSq();
  return sum_sq > 0.0 ? gradient.dot(step) / sum_sq : 0.0;
}

}  // namespace

namespace internal {

cv::Matx33d Skew(const cv::Vec3d& v) { return {0.0, -v[2], v[1], v[2], 0.0, -v[0], -v[1], v[0], 0.0}; }

double RotationAngle(const cv::Vec3d& a, const cv::Vec3d& b) {
  cv::Matx33d ra, rb;
  cv::Rodrigues(a, ra);
  cv::Rodrigues(b, rb);
  return std::acos(std::max(-1.0, std::min(1.0, (cv::trace(ra.t() * rb) - 1.0) / 2.0)));
}

// A camera-frame point P = R X + t has dP/dt = I, so OpenCV's tvec columns are the projection's
// derivative by P for either lens model; a left rotation dtheta moves P by dtheta x P.
bool ProjectWithJacobian(const CameraModel& camera, const std::vector<cv::Point3d>& object, const cv::Vec3d& rvec,
                         const cv::Vec3d& tvec, std::vector<cv::Point2d>& projected, cv::Mat& jacobian) {
  cv::Matx33d rotation;
  cv::Rodrigues(rvec, rotation);
  for (const auto& x : object) {
    if (!((rotation * cv::Vec3d(x.x, x.y, x.z) + tvec)[2] > 0.0)) return false;
  }
  cv::Mat opencv_jacobian;
  int t_column = 3;  // cv::projectPoints: rvec, tvec, f, c, distortion
  if (camera.distortion_model == DistortionModel::kEquidistant) {
    cv::fisheye::projectPoints(object, projected, rvec, tvec, camera.K, camera.distortion, 0.0, opencv_jacobian);
    t_column = 11;  // cv::fisheye::projectPoints: f, c, k1..k4, rvec, tvec, alpha
  } else {
    cv::projectPoints(object, rvec, tvec, camera.K, camera.distortion, projected, opencv_jacobian);
  }
  jacobian.create(static_cast<int>(2 * object.size()), 6, CV_64F);
  for (size_t k = 0; k < object.size(); ++k) {
    projected[k] = camera.pixels.ToImage(projected[k]);
    const cv::Matx33d rotate = -Skew(rotation * cv::Vec3d(object[k].x, object[k].y, object[k].z));
    for (int axis = 0; axis < 2; ++axis) {
      const int row = static_cast<int>(2 * k) + axis;
      const double* j = opencv_jacobian.ptr<double>(row) + t_column;
      const cv::Matx13d by_point = cv::Matx13d(j[0], j[1], j[2]) * (1.0 / camera.pixels.scale[axis]);
      const cv::Matx13d by_rotation = by_point * rotate;
      double* out = jacobian.ptr<double>(row);
      for (int c = 0; c < 3; ++c) {
        out[c] = by_point(0, c);
        out[3 + c] = by_rotation(0, c);
      }
    }
    if (!std::isfinite(projected[k].x) || !std::isfinite(projected[k].y)) return false;
  }
  return cv::checkRange(jacobian);
}

double CornerSigmaPrior(double side_px, bool pattern_fitted) {
  const double side = std::max(side_px, 1.0);
  const auto large = [](double s) {
    return kCornerSigmaPrior * std::pow(std::max(1.0, s / kCornerSigmaPriorSide), kCornerSigmaPriorGrowth);
  };
  if (!pattern_fitted && side < kEdgeCornerSigmaSide) {
    return large(kEdgeCornerSigmaSide) * std::pow(kEdgeCornerSigmaSide / side, kEdgeCornerSigmaGrowth);
  }
  return large(side) * std::pow(std::max(1.0, kCornerSigmaSmallSide / side), 2);
}

double PooledCornerSigma(double sum_sq, double residual_dof, double prior_sigma, double camera_noise) {
  const double prior = kCornerSigmaPriorDof * (prior_sigma * prior_sigma + camera_noise * camera_noise);
  return std::sqrt((prior + sum_sq) / (kCornerSigmaPriorDof + residual_dof));
}

PoseCovariance CovarianceFromNormalMatrix(const cv::Matx66d& jtj, double sigma) {
  cv::Matx66d inverse;
  if (cv::invert(jtj, inverse, cv::DECOMP_CHOLESKY) == 0.0) return UnknownCovariance();
  return inverse * (sigma * sigma);
}

double RivalWeight(double pick_sum_sq, double rival_sum_sq, double corner_sigma) {
  const double sigma = kRivalSigmaScale * corner_sigma;
  if (!std::isfinite(pick_sum_sq) || !std::isfinite(rival_sum_sq) || !(sigma > 0.0)) return 0.0;
  const double evidence = (rival_sum_sq - pick_sum_sq) / (sigma * sigma);  // a chi-square difference
  return 1.0 / (1.0 + std::exp(std::min(0.5 * evidence, 700.0)));
}

PoseCovariance CovarianceWithRival(const PoseEstimate& pick, const PoseEstimate& rival, double weight) {
  if (!(weight > kNegligibleRivalWeight)) return pick.covariance;
  cv::Matx33d r0, r1;
  cv::Rodrigues(pick.rvec, r0);
  cv::Rodrigues(rival.rvec, r1);
  cv::Vec3d turn;
  cv::Rodrigues(r1 * r0.t(), turn);
  const cv::Vec3d shift = rival.tvec - pick.tvec;
  const cv::Vec<double, 6> apart(shift[0], shift[1], shift[2], turn[0], turn[1], turn[2]);
  // A rival whose own neighbourhood is unknown (a singular Jacobian) still counts by its distance.
  const PoseCovariance& around = cv::checkRange(rival.covariance) ? rival.covariance : pick.covariance;
  const PoseCovariance mixed = (1.0 - weight) * pick.covariance + weight * (around + apart * apart.t());
  return cv::checkRange(mixed) ? mixed : pick.covariance;
}

}  // namespace internal

bool EstimatePoseFromPNP(const CameraModel& camera, ArucoTag& tag) {
  camera.Validate();
  const double s = tag.side_length;
  if (!(std::isfinite(s) && s > 0.0)) {
    throw Error("EstimatePoseFromPNP: tag " + std::to_string(tag.id) + " has side length " + std::to_string(s) +
                " m; it must be > 0");
  }
  // SOLVEPNP_IPPE_SQUARE requires exactly this order and centring, which matches cv::aruco's corners.
  const double h = s / 2.0;
  const std::vector<cv::Point3d> object{{-h, h, 0.0}, {h, h, 0.0}, {h, -h, 0.0}, {-h, -h, 0.0}};
  std::vector<cv::Point2d> image;
  for (const auto& c : tag.corners) {
    if (!std::isfinite(c.x) || !std::isfinite(c.y)) return false;
    image.emplace_back(c);
  }
  // Normalized coordinates take binning, ROI and either lens model out of the solver; OpenCV's
  // solvePnPGeneric undistorts to exactly these (cv::undistortPoints) before IPPE or SQPNP anyway.
  std::vector<cv::Point2d> normalized;
  try {
    normalized = camera.Normalize(image);
  } catch (const cv::Exception& e) {
    throw Error(std::string("EstimatePoseFromPNP: OpenCV rejected the camera: ") + e.what());
  }
  for (const auto& p : normalized) {
    // cv::fisheye marks points it cannot undistort (beyond 90 degrees off axis) with huge values.
    if (!std::isfinite(p.x) || !std::isfinite(p.y) || std::abs(p.x) > 1e5 || std::abs(p.y) > 1e5) return false;
  }
  // The errors are measured where the corners were found: in this image's pixels.
  std::vector<Candidate> pair;  // the planar pair, best first
  try {
    std::vector<cv::Mat> rvecs, tvecs;
    const int n = cv::solvePnPGeneric(object, normalized, cv::Matx33d::eye(), cv::noArray(), rvecs, tvecs, false,
                                      cv::SOLVEPNP_IPPE_SQUARE);
    for (int i = 0; i < n; ++i) {
      Candidate c;
      if (Evaluate(camera, object, image, cv::Vec3d(rvecs[i].ptr<double>()), cv::Vec3d(tvecs[i].ptr<double>()), c)) {
        pair.push_back(c);
      }
    }
    const auto by_error = [](const Candidate& a, const Candidate& b) { return a.SumSq() < b.SumSq(); };
    std::stable_sort(pair.begin(), pair.end(), by_error);

    if (pair.empty() || (pair[0].Rms() > kNegligibleRms && OffMinimumShare(pair[0]) > kOffMinimumShare)) {
      // IPPE is off its minimum. Each of its solutions is refined within its own basin, so the pair
      // stays the planar pair; a refinement that lands on the other's minimum is dropped, as it
      // would report one solution twice (and call it ambiguous).
      std::vector<Candidate> refined;
      for (const Candidate& c : pair) {
        cv::Vec3d r = c.rvec, t = c.tvec;
        cv::solvePnPRefineLM(object, normalized, cv::Matx33d::eye(), cv::noArray(), r, t);
        Candidate better;
        const bool ok = Evaluate(camera, object, image, r, t, better) && better.SumSq() < c.SumSq();
        const bool repeat = !refined.empty() && RotationAngle(better.rvec, refined[0].rvec) < kSameMinimumRad;
        refined.push_back(ok && !repeat ? better : c);
      }
      pair = refined;
      // A global solver too, for views where both IPPE solutions sit in wrong basins. It replaces
      // the solution of the pair nearest to it when it does better there, never the other one.
#if CV_VERSION_MAJOR > 4 || (CV_VERSION_MAJOR == 4 && CV_VERSION_MINOR >= 6) || \
    (CV_VERSION_MAJOR == 4 && CV_VERSION_MINOR == 5 && CV_VERSION_REVISION >= 3)
      const auto global_method = cv::SOLVEPNP_SQPNP;  // the global minimum (OpenCV 4.5.3 and later)
#else
      const auto global_method = cv::SOLVEPNP_ITERATIVE;  // homography start, then Levenberg-Marquardt
#endif
      rvecs.clear();
      tvecs.clear();
      const int m = cv::solvePnPGeneric(object, normalized, cv::Matx33d::eye(), cv::noArray(), rvecs, tvecs, false,
                                        global_method);
      for (int i = 0; i < m; ++i) {
        Candidate g;
        if (!Evaluate(camera, object, image, cv::Vec3d(rvecs[i].ptr<double>()), cv::Vec3d(tvecs[i].ptr<double>()), g)) {
          continue;
        }
        if (pair.empty()) {
          pair.push_back(g);
          continue;
        }
        size_t nearest = 0;
        for (size_t k = 1; k < pair.size(); ++k) {
          if (RotationAngle(g.rvec, pair[k].rvec) < RotationAngle(g.rvec, pair[nearest].rvec)) nearest = k;
        }
        if (g.SumSq() < pair[nearest].SumSq()) pair[nearest] = g;
      }
      std::stable_sort(pair.begin(), pair.end(), by_error);
    }
  } catch (const cv::Exception& e) {
    throw Error(std::string("EstimatePoseFromPNP: OpenCV rejected the input: ") + e.what());
  }
  if (pair.empty()) return false;

  PnpResult result;
  // The corners' noise, from the best solution's residual (E[SSE] = 2 sigma^2: 8 coordinates, 6
  // unknowns) pooled with the prior. The second solution's residual is its own misfit, not noise.
  double side_px = 0.0;
  for (size_t k = 0; k < image.size(); ++k) side_px += 0.25 * cv::norm(image[(k + 1) % image.size()] - image[k]);
  result.corner_sigma = internal::PooledCornerSigma(pair[0].SumSq(), 2.0, internal::CornerSigmaPrior(side_px, tag.pattern_fitted),
                                                    camera.corner_noise);
  for (size_t i = 0; i < pair.size() && i < 2; ++i) {
    result.rvec[i] = pair[i].rvec;
    result.tvec[i] = pair[i].tvec;
    result.rms[i] = pair[i].Rms();
    result.covariance[i] =
        internal::CovarianceFromNormalMatrix(pair[i].jacobian.t() * pair[i].jacobian, result.corner_sigma);
    ++result.solutions;
  }
  if (result.solutions == 2) {
    result.ambiguity = result.rms[1] > 0.0 ? result.rms[0] / result.rms[1] : 1.0;
  }
  result.valid = true;
  tag.pnp = result;
  ResolvePose(tag, tag.cloud.valid ? PoseSource::kFused : PoseSource::kPnp);
  return true;
}

namespace {

using internal::Median;
using internal::Sample;

// The marker -> camera rotation of a fitted plane xyz = c + a * ex + b * ey: z the face normal turned
// towards the camera, x along ex.
cv::Matx33d PlaneRotation(const cv::Vec3d& c, const cv::Vec3d& ex, const cv::Vec3d& ey) {
  cv::Vec3d normal = cv::normalize(ex.cross(ey));
  if (normal.dot(c) > 0.0) normal = -normal;  // face the camera whatever the corner order
  const cv::Vec3d x = cv::normalize(ex - ex.dot(normal) * normal);
  const cv::Vec3d y = normal.cross(x);
  return cv::Matx33d(x[0], y[0], normal[0], x[1], y[1], normal[1], x[2], y[2], normal[2]);
}

// Covariance of (c, rotation) of the plane fit: the three coordinates share the design [1 a b], so
// the parameters (c, ex, ey) have covariance (A^T A)^-1 (x) S with S the points' 3x3 noise
// covariance from the inliers' residuals (anisotropic: stereo noise lies along the ray). The
// rotation's derivative by ex and ey is taken numerically. Assumes independent points: a cloud
// whose noise is correlated between neighbours is less certain than this says.
PoseCovariance PlaneCovariance(const std::vector<Sample>& samples, const std::vector<char>& use, const cv::Vec3d& c,
                               const cv::Vec3d& ex, const cv::Vec3d& ey) {
  cv::Matx33d ata = cv::Matx33d::zeros(), noise = cv::Matx33d::zeros();
  int n = 0;
  for (size_t i = 0; i < samples.size(); ++i) {
    if (!use[i]) continue;
    const cv::Vec3d row(1.0, samples[i].a, samples[i].b);
    ata += row * row.t();
    const cv::Vec3d r = samples[i].xyz - (c + samples[i].a * ex + samples[i].b * ey);
    noise += r * r.t();
    ++n;
  }
  cv::Matx33d design;
  if (n <= 3 || cv::invert(ata, design, cv::DECOMP_CHOLESKY) == 0.0) return UnknownCovariance();
  noise *= 1.0 / (n - 3);
  cv::Matx<double, 9, 9> parameters;  // index 3 * p + j: parameter p (c, ex, ey), coordinate j
  for (int p = 0; p < 3; ++p)
    for (int q = 0; q < 3; ++q)
      for (int j = 0; j < 3; ++j)
        for (int k = 0; k < 3; ++k) parameters(3 * p + j, 3 * q + k) = design(p, q) * noise(j, k);
  cv::Matx<double, 6, 9> g = cv::Matx<double, 6, 9>::zeros();
  for (int j = 0; j < 3; ++j) g(j, j) = 1.0;
  const cv::Matx33d rotation = PlaneRotation(c, ex, ey);
  const double step = 1e-6 * cv::norm(ex);
  for (int p = 1; p < 3; ++p) {
    for (int j = 0; j < 3; ++j) {
      cv::Vec3d moved_x = ex, moved_y = ey;
      (p == 1 ? moved_x : moved_y)[j] += step;
      // The small-angle vector of the difference (cv::Rodrigues rounds angles below 1e-5 to 0).
      const cv::Matx33d d = PlaneRotation(c, moved_x, moved_y) * rotation.t();
      const cv::Vec3d dtheta(d(2, 1) - d(1, 2), d(0, 2) - d(2, 0), d(1, 0) - d(0, 1));
      for (int r = 0; r < 3; ++r) g(3 + r, 3 * p + j) = 0.5 * dtheta[r] / step;
    }
  }
  return g * parameters * g.t();
}

// A rotation whose z axis points from the tag back to the camera: the best guess of orientation when
// nothing measured it.
cv::Matx33d FacingCamera(const cv::Vec3d& position) {
  const cv::Vec3d z = -cv::normalize(position);
  cv::Vec3d x = z.cross(cv::Vec3d(0, 1, 0));  // towards-camera x camera-down = marker right
  if (cv::norm(x) < 1e-9) x = cv::Vec3d(1, 0, 0);
  x = cv::normalize(x);
  const cv::Vec3d y = z.cross(x);
  return cv::Matx33d(x[0], y[0], z[0], x[1], y[1], z[1], x[2], y[2], z[2]);
}

}  // namespace

namespace {

// Plane-fit residuals are correlated in patches (stereo block matching): no more independent
// points than this count towards the normal's precision.
constexpr double kMaxIndependentPoints = 25.0;
// Correlated stereo noise: the tag's points move together in patches of about this many points...
constexpr double kPointsPerCentrePatch = 40.0;
// ...no more than this many patches average out in the centre's depth...
constexpr double kCentreIndependentPatches = 25.0;
// ...and the centre moves across the line of sight by this share of its motion along it.
constexpr double kCentreAcrossShare = 0.1;
// The cloud rotation's systematic error (rad) in its covariance. Calibrated on renders, which have
// none: at 1.5 degrees the 1-3 m bin's mean NEES was 1.44. The fused choice assumes much more
// (kNormalSystematic) to stay on the safe side with real depth-to-colour calibrations.
constexpr double kRotationSystematic = 0.5 * CV_PI / 180.0;
// A normal from noise alone is still a direction facing the camera: its error is bounded.
constexpr double kMaxRotationSigma = 0.8;
// Corner noise never assumed below this (px): the edge and pattern fits reach 0.03-0.09 px (p95) on
// renders; real, compressed images are noisier.
constexpr double kMinCornerSigma = 0.1;
// The cloud overrides the corners when its evidence for the other solution exceeds theirs for the
// pick by this much (a chi-square difference: 9 = three standard deviations)...
constexpr double kDecisiveEvidence = 9.0;
// ...and the two normals it compares differ from the cloud's by at least this much.
constexpr double kMinNormalMargin = 2.0 * CV_PI / 180.0;
// A clear pick, whose rival reprojects over five times worse (`ambiguity`, the ratio of the two
// RMS errors, below this), is overturned only by a plane whose normal is known to within twice its
// systematic error (kNormalSystematic, below). The corners' chi-square understates such a pick when
// its fit is far below the corner-noise floor, and a noisy plane's correlated patches can tilt it
// onto the other solution: bench_pose seed 17, frame 303, a 17 px marker at 7.9 m, 0.001 against
// 0.078 px (ambiguity 0.008), a plane 9 degrees from the rival with 25 degrees of noise, turned
// 105 degrees. Over 4000 frames (seeds 7, 11, 13, 17, bench_pose --csv) every pick the cloud
// rightly overturned had an ambiguity of 0.25 or more.
constexpr double kClearPickAmbiguity = 0.2;
constexpr double kClearPickNormalSystematics = 2.0;
// A real cloud's normal is off by more than its noise says: blocks averaged across the marker's
// edge, a cloud a frame older than the image on a turning rover, calibration. This much (rad) is
// added in quadrature. Without it the sample recording's fused poses flipped 13 times where PnP
// alone flipped none.
constexpr double kNormalSystematic = 5.0 * CV_PI / 180.0;
// A plane further than this from the solution it favours, or twice its own standard deviation if
// that is more, is not this marker's face (the ground or a post behind a small marker, a cloud
// misregistered by motion): it says nothing about the choice. A fixed 15 degrees alone turned away
// a stereo plane 20 degrees off at 9 m, where its noise was 33 degrees, and left PnP's flip (bench_pose
// seed 7, frame 571); with twice the sigma, 4000 frames (seeds 7, 11, 13, 17) flip 0 / 0 / 3 / 74 times
// per range bin against 0 / 2 / 5 / 74 with 15 degrees and PnP's 0 / 5 / 7 / 74 (IPPE solutions
// picked; bench_pose --csv). One flip of the fused choice is left in both (seed 17, frame 303): a
// correlated stereo patch tilted a 17 px tag's plane at 7.9 m onto the wrong solution.
constexpr double kMaxPlaneDisagreement = 15.0 * CV_PI / 180.0;
constexpr double kPlaneDisagreementSigmas = 2.0;

// Standard deviation (rad) of the fitted plane's normal: depth noise (the plane residuals, at least
// the camera's model at that range) over the
// lever arm of the points (uniform over the shrunk square: sd side / sqrt(12) per axis), plus the
// systematic part.
double NormalSigma(const ArucoTag& tag, const CloudResult& cloud, const CloudPoseOptions& options) {
  const double extent = tag.side_length * (1.0 - options.shrink) / std::sqrt(12.0);
  const double n = std::min<double>(cloud.points, kMaxIndependentPoints);
  if (!std::isfinite(cloud.plane_rms) || extent <= 0.0 || n < 3.0) return CV_PI;
  // Correlated noise looks like a tilt of the whole patch and leaves small residuals: the camera's
  // own depth noise at that range is the floor.
  const double z = cv::norm(cloud.centre);
  const double depth_sigma = std::max({cloud.plane_rms, options.depth_noise_per_m2 * z * z, 1e-4});
  return std::hypot(depth_sigma / (extent * std::sqrt(n)), kNormalSystematic);
}

// The plane fit's covariance (independent points) widened by what correlated stereo noise does: the
// whole patch moves along the line of sight by about the camera's depth noise at that range over
// the square root of the independent patches on the tag, and a tenth of that across it; the face
// tilts by the normal's sigma about any axis (the in-plane direction comes from the same points'
// depths), with a smaller systematic part than the fused choice's (kRotationSystematic), and at
// most kMaxRotationSigma. Cross terms between centre and rotation are dropped with the widening.
// On 1000 rendered frames with a ZED 2's noise (bench_pose) this brings the cloud's mean NEES per
// range bin from hundreds-thousands (the plane fit's alone) into [1.5, 6].
PoseCovariance CloudCovariance(const PoseCovariance& plane, const CloudResult& cloud, const CloudPoseOptions& options) {
  if (!std::isfinite(plane(0, 0))) return plane;
  const double z = cv::norm(cloud.centre);
  const double patches = std::clamp(cloud.points / kPointsPerCentrePatch, 1.0, kCentreIndependentPatches);
  const double along = options.depth_noise_per_m2 * z * z / std::sqrt(patches);
  const double across = kCentreAcrossShare * along;
  const cv::Vec3d ray = cloud.centre / std::max(z, 1e-9);
  const double tilt_noise = std::sqrt(std::max(0.0, std::pow(cloud.normal_sigma, 2) - std::pow(kNormalSystematic, 2)));
  const double tilt = std::min(std::hypot(tilt_noise, kRotationSystematic), kMaxRotationSigma);
  PoseCovariance covariance = PoseCovariance::zeros();
  for (int i = 0; i < 3; ++i) {
    for (int j = 0; j < 3; ++j) {
      const double identity = i == j ? 1.0 : 0.0;
      covariance(i, j) = plane(i, j) + along * along * ray[i] * ray[j] + across * across * (identity - ray[i] * ray[j]);
      covariance(3 + i, 3 + j) = plane(3 + i, 3 + j) + identity * tilt * tilt;
    }
  }
  return covariance;
}

// An organized cloud's points wherever they lie in memory: pixel (u, v)'s x, y, z are the three
// floats at data + v * row_step + u * point_step. Both overloads read through it.
struct CloudView {
  const unsigned char* data;
  size_t row_step, point_step;
  cv::Size size;
  const float* At(int u, int v) const {
    return reinterpret_cast<const float*>(data + static_cast<size_t>(v) * row_step +
                                          static_cast<size_t>(u) * point_step);
  }
};

bool EstimatePoseFromCloudView(const CloudView& cloud, ArucoTag& tag, const CloudPoseOptions& options) {
  const cv::Size image_size = cloud.size;
  tag.cloud = CloudResult();

  std::vector<cv::Point2f> image_quad(tag.corners.begin(), tag.corners.end());
  const std::vector<cv::Point2f> marker_quad{{-0.5f, 0.5f}, {0.5f, 0.5f}, {0.5f, -0.5f}, {-0.5f, -0.5f}};
  const cv::Matx33d to_marker = cv::getPerspectiveTransform(image_quad, marker_quad);
  const cv::Rect box = cv::boundingRect(image_quad) & cv::Rect(cv::Point(0, 0), image_size);
  const double limit = 0.5 * (1.0 - options.shrink);

  std::vector<Sample> samples;
  for (int v = box.y; v < box.y + box.height; ++v) {
    for (int u = box.x; u < box.x + box.width; ++u) {
      const cv::Vec3d m = to_marker * cv::Vec3d(u, v, 1.0);
      if (!(std::abs(m[2]) > 1e-12)) continue;
      const double a = m[0] / m[2], b = m[1] / m[2];
      if (std::abs(a) > limit || std::abs(b) > limit) continue;
      const float* p = cloud.At(u, v);
      if (!std::isfinite(p[0]) || !std::isfinite(p[1]) || !std::isfinite(p[2]) || !(p[2] > 0.0f)) continue;
      samples.push_back({a, b, cv::Vec3d(p[0], p[1], p[2])});
    }
  }
  // Thin out close (large) tags after collecting, so sparse clouds keep every point they have;
  // accuracy is limited by depth noise, not by the point count.
  if (options.max_samples > 0 && static_cast<int>(samples.size()) > options.max_samples) {
    const size_t step = (samples.size() + options.max_samples - 1) / options.max_samples;
    size_t kept = 0;
    for (size_t i = 0; i < samples.size(); i += step) samples[kept++] = samples[i];
    samples.resize(kept);
  }
  // Not one point, whatever min_points says: the medians below need one (fuzz_pose, min_points 0).
  if (samples.empty() || static_cast<int>(samples.size()) < options.min_points) {
    // The old cloud result is gone: keep the pose consistent with what is still measured.
    ResolvePose(tag, tag.pnp.valid ? PoseSource::kPnp : PoseSource::kNone);
    return false;
  }

  CloudResult& result = tag.cloud;
  internal::MarkerPlane plane;
  const bool fitted = internal::FitMarkerPlane(samples, options, plane);
  const std::vector<char>& use = plane.use;
  const cv::Vec3d &c = plane.c, &ex = plane.ex, &ey = plane.ey;

  if (fitted) {
    result.points = static_cast<int>(std::count(use.begin(), use.end(), 1));
    result.centre = c;
    result.rotation = PlaneRotation(c, ex, ey);
    const cv::Vec3d normal(result.rotation(0, 2), result.rotation(1, 2), result.rotation(2, 2));
    result.normal = normal;
    result.has_normal = true;
    result.has_rotation = true;
    double sum_sq = 0.0;
    for (size_t i = 0; i < samples.size(); ++i) {
      if (use[i]) sum_sq += std::pow((samples[i].xyz - c).dot(normal), 2);
    }
    result.plane_rms = std::sqrt(sum_sq / result.points);
    result.normal_sigma = NormalSigma(tag, result, options);
    result.covariance = CloudCovariance(PlaneCovariance(samples, use, c, ex, ey), result, options);
  } else {
    // Too few points for a plane: the per-axis median is still robust to flying pixels.
    std::vector<double> xs, ys, zs;
    for (const auto& s : samples) {
      xs.push_back(s.xyz[0]);
      ys.push_back(s.xyz[1]);
      zs.push_back(s.xyz[2]);
    }
    result.points = static_cast<int>(samples.size());
    result.centre = cv::Vec3d(Median(xs), Median(ys), Median(zs));
    // The median's variance is pi/2 times the mean's; the points' spread (MAD) stands for their
    // noise and for where on the tag they happen to lie. Nothing measured the orientation.
    result.covariance = PoseCovariance::zeros();
    const std::vector<double>* axes[3] = {&xs, &ys, &zs};
    for (int j = 0; j < 3; ++j) {
      std::vector<double> deviation;
      for (double v : *axes[j]) deviation.push_back(std::abs(v - result.centre[j]));
      const double spread = 1.4826 * Median(deviation);
      result.covariance(j, j) = CV_PI / 2.0 * spread * spread / result.points;
      result.covariance(3 + j, 3 + j) = CV_PI * CV_PI;
    }
  }
  result.valid = true;
  ResolvePose(tag, tag.pnp.valid ? PoseSource::kFused : PoseSource::kPointCloud);
  return true;
}

}  // namespace

bool EstimatePoseFromPointCloud(const cv::Mat& cloud, const cv::Size& image_size, ArucoTag& tag,
                                const CloudPoseOptions& options) {
  if (cloud.type() != CV_32FC3) {
    throw Error("EstimatePoseFromPointCloud: cloud must be an organized CV_32FC3 (XYZ) matrix");
  }
  if (cloud.size() != image_size) {
    throw Error("EstimatePoseFromPointCloud: cloud is " + std::to_string(cloud.cols) + "x" +
                std::to_string(cloud.rows) + " but the image is " + std::to_string(image_size.width) + "x" +
                std::to_string(image_size.height) + "; an organized cloud must match the image pixel for pixel");
  }
  return EstimatePoseFromCloudView({cloud.data, cloud.step[0], sizeof(cv::Vec3f), image_size}, tag, options);
}

bool EstimatePoseFromPointCloud(const pcl::PointCloud<pcl::PointXYZ>& cloud, ArucoTag& tag,
                                const CloudPoseOptions& options) {
  const cv::Size size(static_cast<int>(cloud.width), static_cast<int>(cloud.height));
  if (cloud.height <= 1) {
    throw Error("EstimatePoseFromPointCloud: the PCL cloud is not organized (" + std::to_string(cloud.width) + "x" +
                std::to_string(cloud.height) + "); it must hold one point per image pixel");
  }
  if (cloud.points.size() != static_cast<size_t>(size.area())) {
    throw Error("EstimatePoseFromPointCloud: the PCL cloud is " + std::to_string(cloud.width) + "x" +
                std::to_string(cloud.height) + " but holds " + std::to_string(cloud.points.size()) + " points");
  }
  return EstimatePoseFromCloudView({reinterpret_cast<const unsigned char*>(cloud.points.data()),
                                    sizeof(pcl::PointXYZ) * cloud.width, sizeof(pcl::PointXYZ), size},
                                   tag, options);
}

FusedEvidence WeighFusedEvidence(const ArucoTag& tag) {
  // IPPE's two solutions differ mainly by a reflection of the face normal about the line of sight.
  // Each measurement's evidence is a chi-square difference between the two solutions under its own
  // noise: the corners' from the reprojection errors (8 residuals, 6 unknowns: a solution's RMS is
  // about half the corner noise), the cloud's from the angles between its normal and each
  // solution's.
  FusedEvidence evidence;
  if (!tag.cloud.has_normal || tag.pnp.solutions < 2) return evidence;
  const double e0 = tag.pnp.rms[0], e1 = tag.pnp.rms[1];
  if (!std::isfinite(e0) || !std::isfinite(e1)) return evidence;
  // When the corners mislead, the wrong solution has absorbed the noise and the better fit's
  // residual understates it: the floor is the corner noise of real images.
  const double corner_sigma = std::max(2.0 * std::min(e0, e1), kMinCornerSigma);
  evidence.corners = 8.0 * (e1 * e1 - e0 * e0) / (corner_sigma * corner_sigma);
  for (int i = 0; i < 2; ++i) {
    cv::Matx33d r;
    cv::Rodrigues(tag.pnp.rvec[i], r);
    const double c = cv::Vec3d(r(0, 2), r(1, 2), r(2, 2)).dot(tag.cloud.normal);
    evidence.angle[i] = std::acos(std::max(-1.0, std::min(1.0, c)));
  }
  evidence.normal_sigma = std::isfinite(tag.cloud.normal_sigma) ? tag.cloud.normal_sigma : CV_PI;
  evidence.cloud = (evidence.angle[0] * evidence.angle[0] - evidence.angle[1] * evidence.angle[1]) /
                   (evidence.normal_sigma * evidence.normal_sigma);
  evidence.usable = true;
  return evidence;
}

int FusedChoice(const ArucoTag& tag) {
  // The cloud overrides the corners' pick only when its evidence clearly outweighs theirs, so a
  // noisy or stale cloud does not flip a good PnP pose, and a confident plane fixes an ambiguous one.
  const FusedEvidence evidence = WeighFusedEvidence(tag);
  if (!evidence.usable) return 0;
  const bool clear_pick = tag.pnp.rms[0] < kClearPickAmbiguity * tag.pnp.rms[1];
  if (clear_pick && evidence.normal_sigma > kClearPickNormalSystematics * kNormalSystematic) return 0;
  const double plane_limit = std::max(kMaxPlaneDisagreement, kPlaneDisagreementSigmas * evidence.normal_sigma);
  if (evidence.angle[0] - evidence.angle[1] < kMinNormalMargin || evidence.angle[1] > plane_limit) return 0;
  return evidence.cloud - evidence.corners > kDecisiveEvidence ? 1 : 0;
}

namespace {

// Squared Mahalanobis distance (3 degrees of freedom) beyond which the cloud's centre is not fused:
// the chi-square 99.9 % point.
constexpr double kCentreGate = 16.27;

// Kalman update of a pose (tvec, rvec, covariance: see PoseCovariance) by a direct measurement of
// its centre. False, pose untouched, when either covariance is unknown or singular or the centre
// fails the gate.
bool FuseCentre(const cv::Vec3d& centre, const PoseCovariance& centre_covariance, cv::Vec3d& tvec, cv::Vec3d& rvec,
                PoseCovariance& covariance) {
  cv::Matx33d innovation_covariance;
  cv::Matx<double, 6, 3> pose_centre;  // covariance of the pose with its centre
  for (int i = 0; i < 6; ++i) {
    for (int j = 0; j < 3; ++j) {
      pose_centre(i, j) = covariance(i, j);
      if (i < 3) innovation_covariance(i, j) = covariance(i, j) + centre_covariance(i, j);
    }
  }
  cv::Matx33d inverse;
  if (!cv::checkRange(innovation_covariance) ||
      cv::invert(innovation_covariance, inverse, cv::DECOMP_CHOLESKY) == 0.0) {
    return false;
  }
  const cv::Vec3d innovation = centre - tvec;
  if ((innovation.t() * inverse * innovation)(0) > kCentreGate) return false;
  const cv::Matx<double, 6, 3> gain = pose_centre * inverse;
  const cv::Vec<double, 6> step = gain * innovation;
  tvec += cv::Vec3d(step[0], step[1], step[2]);
  cv::Matx33d rotation, turn;
  cv::Rodrigues(rvec, rotation);
  cv::Rodrigues(cv::Vec3d(step[3], step[4], step[5]), turn);
  cv::Rodrigues(turn * rotation, rvec);
  covariance -= gain * pose_centre.t();
  covariance = 0.5 * (covariance + covariance.t());
  return true;
}

// The covariance of PnP's pick (solution 0) with its rival planar solution weighed in by the corners'
// likelihood of it (internal::CovarianceWithRival).
PoseCovariance PickCovariance(const PnpResult& pnp) {
  if (pnp.solutions < 2) return pnp.covariance[0];
  const double weight =
      internal::RivalWeight(8.0 * pnp.rms[0] * pnp.rms[0], 8.0 * pnp.rms[1] * pnp.rms[1], pnp.corner_sigma);
  return internal::CovarianceWithRival({pnp.rvec[0], pnp.tvec[0], pnp.covariance[0]},
                                       {pnp.rvec[1], pnp.tvec[1], pnp.covariance[1]}, weight);
}

}  // namespace

PoseSource ResolvePose(ArucoTag& tag, PoseSource wanted) {
  const bool pnp = tag.pnp.valid && tag.pnp.solutions > 0;
  const bool cloud = tag.cloud.valid;
  PoseSource source = wanted;
  if (source == PoseSource::kFused && !(pnp && cloud)) source = pnp ? PoseSource::kPnp : PoseSource::kPointCloud;
  if (source == PoseSource::kPnp && !pnp) source = PoseSource::kPointCloud;
  if (source == PoseSource::kPointCloud && !cloud) source = pnp ? PoseSource::kPnp : PoseSource::kNone;

  const double nan = std::numeric_limits<double>::quiet_NaN();
  tag.pose_source = source;
  tag.reprojection_error = nan;
  tag.covariance = UnknownCovariance();
  tag.orientation_measured = source != PoseSource::kNone;
  tag.depth_disagreement = pnp && cloud ? std::abs(cv::norm(tag.pnp.tvec[0]) - cv::norm(tag.cloud.centre)) : nan;
  switch (source) {
    case PoseSource::kNone:
      tag.rvec = tag.tvec = cv::Vec3d();
      tag.distance = tag.yaw = nan;
      return source;
    case PoseSource::kPnp:
      tag.rvec = tag.pnp.rvec[0];
      tag.tvec = tag.pnp.tvec[0];
      tag.reprojection_error = tag.pnp.rms[0];
      tag.covariance = PickCovariance(tag.pnp);
      break;
    case PoseSource::kPointCloud: {
      tag.tvec = tag.cloud.centre;
      tag.covariance = tag.cloud.covariance;
      cv::Matx33d rotation;
      if (tag.cloud.has_rotation) {
        rotation = tag.cloud.rotation;
      } else if (pnp) {
        cv::Rodrigues(tag.pnp.rvec[0], rotation);
        // Two independent measurements: the cloud's centre, PnP's rotation.
        const PoseCovariance pick = PickCovariance(tag.pnp);
        for (int i = 0; i < 6; ++i) {
          for (int j = 0; j < 6; ++j) {
            if (i >= 3 || j >= 3) tag.covariance(i, j) = i >= 3 && j >= 3 ? pick(i, j) : 0.0;
          }
        }
      } else {
        rotation = FacingCamera(tag.cloud.centre);
        tag.orientation_measured = false;
      }
      cv::Rodrigues(rotation, tag.rvec);
      break;
    }
    case PoseSource::kFused: {
      const int best = FusedChoice(tag);
      tag.rvec = tag.pnp.rvec[best];
      tag.tvec = tag.pnp.tvec[best];
      tag.reprojection_error = tag.pnp.rms[best];
      // A cloud without a plane says nothing about the flip: the corners' rival stays as likely.
      tag.covariance = tag.cloud.has_normal ? tag.pnp.covariance[best] : PickCovariance(tag.pnp);
      tag.depth_disagreement = std::abs(cv::norm(tag.tvec) - cv::norm(tag.cloud.centre));
      // The cloud's centre then updates the chosen solution, weighed by the two covariances
      // (through PnP's centre-rotation correlation it moves the rotation too); a centre that
      // disagrees beyond the gate is another surface, a stale cloud or a misregistration, and is
      // left out.
      FuseCentre(tag.cloud.centre, tag.cloud.covariance, tag.tvec, tag.rvec, tag.covariance);
      break;
    }
  }
  tag.distance = cv::norm(tag.tvec);
  tag.yaw = std::atan2(tag.tvec[0], tag.tvec[2]);
  return source;
}

}  // namespace arucotag

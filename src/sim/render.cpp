// Synthetic ArUco scene renderer: per-sample ray casting against marker planes,
// so edges/corners are exact to the supersampling limit, plus seeded clutter,
// photometric degradations, exact depth and an organized point cloud.
#include "arucotag/sim.hpp"

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <limits>
#include <numeric>

#include <opencv2/calib3d.hpp>
#include <opencv2/imgproc.hpp>

namespace arucotag::sim {
namespace {

constexpr double kDeg = CV_PI / 180.0;

// A fisheye lens bends rays even with all-zero coefficients (r = f * theta).
bool HasDistortion(const Camera& cam) {
  return cam.fisheye ||
         std::any_of(cam.dist.begin(), cam.dist.end(), [](double d) { return d != 0.0; });
}

cv::Mat DistMat(const Camera& cam) {
  if (cam.fisheye) return cam.dist.empty() ? cv::Mat::zeros(4, 1, CV_64F) : cv::Mat(cam.dist, true);
  return HasDistortion(cam) ? cv::Mat(cam.dist, true) : cv::Mat();
}

// Image positions of camera-frame points moved by (rvec, tvec), through either lens model.
std::vector<cv::Point2d> Project(const Camera& cam, const std::vector<cv::Point3d>& pts,
                                 const cv::Vec3d& rvec, const cv::Vec3d& tvec) {
  std::vector<cv::Point2d> img;
  if (cam.fisheye)
    cv::fisheye::projectPoints(pts, img, rvec, tvec, cam.K, DistMat(cam));
  else
    cv::projectPoints(pts, rvec, tvec, cam.K, DistMat(cam), img);
  return img;
}

// Normalized rays (x, y) of pixel positions (CV_64FC2 in and out). The
// pinhole inverse runs a fixed iteration count only (no EPS) so OpenCV skips
// its per-iteration reprojection; 40 iterations converge far below 1e-6 px
// for sane lenses. cv::fisheye solves theta by Newton's method to 1e-8 rad
// (its criteria argument is newer than OpenCV 4.2).
void Undistort(const Camera& cam, const cv::Mat& px, cv::Mat& rays) {
  if (cam.fisheye)
    cv::fisheye::undistortPoints(px, rays, cam.K, DistMat(cam));
  else
    cv::undistortPoints(px, rays, cam.K, DistMat(cam), cv::noArray(), cv::noArray(),
                        cv::TermCriteria(cv::TermCriteria::COUNT, 40, 0));
}

// Normalized (undistorted) rays for pixel positions. Without distortion the
// inverse of K is exact; with it, rays are undistorted on the integer pixel
// grid covering `region` (plus one pixel each side) once and bilinearly
// interpolated in between: the distortion field's curvature over one pixel is
// ~1e-4 px, far below the 0.01 px budget, and it avoids undistorting 64
// samples per pixel.
class RayMap {
 public:
  RayMap(const Camera& cam, cv::Rect region) : k_inv_(cam.K.inv()), distorted_(HasDistortion(cam)) {
    if (!distorted_) return;
    x0_ = region.x - 1;
    y0_ = region.y - 1;
    gw_ = region.width + 2;
    gh_ = region.height + 2;
    grid_.resize(static_cast<size_t>(gw_) * gh_);
    // Rows are independent, so chunks run in parallel.
    cv::parallel_for_(cv::Range(0, gh_), [&](const cv::Range& rows) {
      std::vector<cv::Point2d> px;
      for (int j = rows.start; j < rows.end; ++j)
        for (int i = 0; i < gw_; ++i) px.emplace_back(x0_ + i, y0_ + j);
      cv::Point2d* out = &grid_[static_cast<size_t>(rows.start) * gw_];
      cv::Mat dst(static_cast<int>(px.size()), 1, CV_64FC2, out);
      Undistort(cam, cv::Mat(px), dst);
      CV_Assert(dst.ptr<cv::Point2d>() == out);  // written in place, not reallocated
    });
  }

  // Takes a pixel position inside [-1, w] x [-1, h]; returns (x, y) with ray (x, y, 1).
  cv::Vec2d operator()(double u, double v) const {
    if (!distorted_) {
      const cv::Vec3d r = k_inv_ * cv::Vec3d(u, v, 1.0);
      return {r[0] / r[2], r[1] / r[2]};
    }
    const double gu = std::clamp(u - x0_, 0.0, gw_ - 1.000001);
    const double gv = std::clamp(v - y0_, 0.0, gh_ - 1.000001);
    const int iu = static_cast<int>(gu), iv = static_cast<int>(gv);
    const double fu = gu - iu, fv = gv - iv;
    const cv::Point2d* p = &grid_[static_cast<size_t>(iv) * gw_ + iu];
    const cv::Point2d a = p[0] * (1 - fu) + p[1] * fu;
    const cv::Point2d b = p[gw_] * (1 - fu) + p[gw_ + 1] * fu;
    const cv::Point2d r = a * (1 - fv) + b * fv;
    return {r.x, r.y};
  }

 private:
  cv::Matx33d k_inv_;
  bool distorted_;
  int x0_ = 0, y0_ = 0, gw_ = 0, gh_ = 0;
  std::vector<cv::Point2d> grid_;
};

// A marker reduced to what the per-sample inner loop needs: a homography from
// the normalized ray (x, y, 1) to marker-plane coordinates and the bit grid.
struct PreparedMarker {
  cv::Vec3d h1, h2, h3;  // X = h1.d / h3.d, Y = h2.d / h3.d
  double c = 0;          // lambda = c / h3.d (c < 0: printed face visible)
  double half_side = 0, half_outer = 0, cell = 0;
  cv::Mat bits;  // CV_8U, 255 = white, incl. the 1-cell black border
  cv::Rect box;  // pixels that may see the quiet-zone quad
};

PreparedMarker Prepare(const Camera& cam, const Marker& m, const cv::Mat& bits, double quiet_zone) {
  PreparedMarker p;
  cv::Matx33d r;
  cv::Rodrigues(m.rvec, r);
  const cv::Vec3d r1(r(0, 0), r(1, 0), r(2, 0)), r2(r(0, 1), r(1, 1), r(2, 1)),
      r3(r(0, 2), r(1, 2), r(2, 2));
  p.c = r3.dot(m.tvec);
  p.h1 = p.c * r1 - r1.dot(m.tvec) * r3;
  p.h2 = p.c * r2 - r2.dot(m.tvec) * r3;
  p.h3 = r3;
  p.bits = bits;
  p.cell = m.side / bits.cols;
  p.half_side = m.side / 2;
  p.half_outer = p.half_side + quiet_zone * p.cell;

  // Bounding box of the outer quad, clipped to the half-space in front of the
  // camera so markers partly behind it stay cheap, and sampled along its edges
  // because edges bow under distortion (a fisheye's strongly). With pinhole
  // distortion, points far outside the field of view project meaninglessly
  // (the polynomial folds back), so such markers fall back to the whole image;
  // an equidistant lens maps the whole half-space in front monotonically.
  const cv::Rect full(cv::Point(0, 0), cam.size);
  constexpr double kNear = 1e-4;
  const double h = p.half_outer;
  const cv::Vec3d quad[4] = {r * cv::Vec3d(-h, h, 0) + m.tvec, r * cv::Vec3d(h, h, 0) + m.tvec,
                             r * cv::Vec3d(h, -h, 0) + m.tvec, r * cv::Vec3d(-h, -h, 0) + m.tvec};
  std::vector<cv::Vec3d> poly;  // Sutherland-Hodgman against z >= kNear
  for (int e = 0; e < 4; ++e) {
    const cv::Vec3d& a = quad[e];
    const cv::Vec3d& b = quad[(e + 1) % 4];
    if (a[2] >= kNear) poly.push_back(a);
    if ((a[2] >= kNear) != (b[2] >= kNear))
      poly.push_back(a + (b - a) * ((kNear - a[2]) / (b[2] - a[2])));
  }
  if (poly.empty()) return p;  // entirely behind the camera: empty box
  const bool distorted = HasDistortion(cam);
  const int per_edge = cam.fisheye ? 64 : distorted ? 16 : 1;
  const double max_tan =
      4.0 * std::max(cam.size.width / cam.K(0, 0), cam.size.height / cam.K(1, 1));
  std::vector<cv::Point3d> pts;
  for (size_t e = 0; e < poly.size(); ++e)
    for (int i = 0; i < per_edge; ++i) {
      const cv::Vec3d q =
          poly[e] + (poly[(e + 1) % poly.size()] - poly[e]) * (double(i) / per_edge);
      if (distorted && !cam.fisheye && std::hypot(q[0], q[1]) > max_tan * q[2]) {
        p.box = full;
        return p;
      }
      pts.emplace_back(q[0], q[1], q[2]);
    }
  const std::vector<cv::Point2d> img = Project(cam, pts, cv::Vec3d(), cv::Vec3d());
  double x0 = img[0].x, y0 = img[0].y, x1 = x0, y1 = y0;
  for (const auto& q : img) {
    x0 = std::min(x0, q.x), x1 = std::max(x1, q.x);
    y0 = std::min(y0, q.y), y1 = std::max(y1, q.y);
  }
  // Clamp in double first: near-plane points project to huge coordinates.
  auto lo = [](double t, int n) {
    return static_cast<int>(std::floor(std::clamp(t, -4.0, n + 4.0))) - 2;
  };
  auto hi = [](double t, int n) {
    return static_cast<int>(std::ceil(std::clamp(t, -4.0, n + 4.0))) + 3;
  };
  p.box = cv::Rect(cv::Point(lo(x0, cam.size.width), lo(y0, cam.size.height)),
                   cv::Point(hi(x1, cam.size.width), hi(y1, cam.size.height))) &
          full;
  return p;
}

// Sub-pixel sampling: n*n points of a rank-1 lattice {k/N, k*gen/N} (N = n*n)
// replace the regular n x n grid. All N points have distinct x and distinct
// y, so axis-aligned edges (frontal markers, the common test case) are
// resolved to 1/(2N) px instead of 1/(2n) px; the generator maximizing the
// smallest point spacing keeps every other direction as good as the grid.
// A per-pixel random (hashed, deterministic) toroidal shift makes each
// pixel's coverage an unbiased estimate, so the residual error is zero-mean
// noise that averages out along an edge instead of a systematic edge shift.
int Rank1Generator(int n2) {
  int best_gen = 1;
  double best_d = -1;
  for (int g = 1; g < n2; ++g) {
    if (std::gcd(g, n2) != 1) continue;
    double d = 1e9;
    for (int k = 1; k < n2; ++k) {
      double x = double(k) / n2, y = double(static_cast<int64_t>(k) * g % n2) / n2;
      x = std::min(x, 1 - x);
      y = std::min(y, 1 - y);
      d = std::min(d, x * x + y * y);
    }
    if (d > best_d) best_d = d, best_gen = g;
  }
  return best_gen;
}

// Deterministic hash of a pixel (and a stream index) to [0, 1).
double PixelHash(int u, int v, int stream) {
  uint64_t h = (uint64_t(uint32_t(u)) << 32) ^ uint32_t(v) ^ (uint64_t(stream) << 62);
  h ^= h >> 33;
  h *= 0xff51afd7ed558ccdULL;
  h ^= h >> 33;
  h *= 0xc4ceb9fe1a85ec53ULL;
  h ^= h >> 33;
  return double(h >> 11) * (1.0 / 9007199254740992.0);
}

// Grey value and depth of the nearest surface along ray (x, y, 1) among the
// candidate markers; returns false when only the wall is hit.
bool CastRay(const std::vector<const PreparedMarker*>& cand, double x, double y, double wall,
             double white, double black, double* grey, double* z) {
  double best = wall;
  bool hit = false;
  for (const PreparedMarker* p : cand) {
    const double den = p->h3[0] * x + p->h3[1] * y + p->h3[2];
    if (den == 0.0) continue;
    const double inv_den = 1.0 / den;
    const double lam = p->c * inv_den;  // ray parameter == optical z because d_z = 1
    if (lam <= 0.0 || lam >= best) continue;
    const double mx = (p->h1[0] * x + p->h1[1] * y + p->h1[2]) * inv_den;
    const double my = (p->h2[0] * x + p->h2[1] * y + p->h2[2]) * inv_den;
    if (std::abs(mx) > p->half_outer || std::abs(my) > p->half_outer) continue;
    best = lam;
    hit = true;
    if (p->c >= 0.0) {  // seen from behind: blank paper
      *grey = white;
      continue;
    }
    const int col = static_cast<int>(std::floor((mx + p->half_side) / p->cell));
    const int row = static_cast<int>(std::floor((p->half_side - my) / p->cell));
    const bool inside = col >= 0 && row >= 0 && col < p->bits.cols && row < p->bits.rows;
    *grey = (!inside || p->bits.ptr<uchar>(row)[col]) ? white : black;
  }
  *z = best;
  return hit;
}

// Exact shortcut for pixels that every sub-sample would see identically,
// decided from the rays through the pixel's four corners. It relies on
// convexity: the pixel maps into each marker plane as a convex quad when the
// plane's horizon does not cross it, inverse depth 1/lambda = h3.d / c is
// affine in the ray so "in front of" is a half-plane, and marker cells
// (quiet-zone cells included) are convex. Returns true if the pixel is
// uniform, with *hit telling marker vs wall and *grey the marker's grey.
bool UniformPixel(const std::vector<const PreparedMarker*>& cand, const cv::Vec2d (&d)[4],
                  double wall, double white, double black, bool* hit, double* grey) {
  const PreparedMarker* near = nullptr;
  int cell_row = 0, cell_col = 0;
  double inv_lam[4];  // inverse depth of the nearest marker at each corner
  for (int k = 0; k < 4; ++k) {
    const PreparedMarker* nk = nullptr;
    double best = wall;
    int r = 0, c = 0;
    for (const PreparedMarker* p : cand) {
      const double den = p->h3[0] * d[k][0] + p->h3[1] * d[k][1] + p->h3[2];
      if (den == 0.0) continue;
      const double lam = p->c / den;
      if (lam <= 0.0 || lam >= best) continue;
      const double mx = (p->h1[0] * d[k][0] + p->h1[1] * d[k][1] + p->h1[2]) / den;
      const double my = (p->h2[0] * d[k][0] + p->h2[1] * d[k][1] + p->h2[2]) / den;
      if (std::abs(mx) > p->half_outer || std::abs(my) > p->half_outer) continue;
      best = lam;
      nk = p;
      c = p->c >= 0.0 ? 0 : static_cast<int>(std::floor((mx + p->half_side) / p->cell));
      r = p->c >= 0.0 ? 0 : static_cast<int>(std::floor((p->half_side - my) / p->cell));
    }
    if (k > 0 && (nk != near || r != cell_row || c != cell_col)) return false;
    near = nk, cell_row = r, cell_col = c;
    inv_lam[k] = 1.0 / best;
  }
  for (const PreparedMarker* p : cand) {
    if (p == near) continue;
    // Harmless if its plane is nowhere in front of the visible surface ...
    bool behind = true, same_sign = true;
    int out[4] = {0, 0, 0, 0};  // corners beyond +x, -x, +y, -y of its outer square
    for (int k = 0; k < 4; ++k) {
      const double den = p->h3[0] * d[k][0] + p->h3[1] * d[k][1] + p->h3[2];
      behind &= p->c == 0.0 || den / p->c <= inv_lam[k];
      const double den0 = p->h3[0] * d[0][0] + p->h3[1] * d[0][1] + p->h3[2];
      same_sign &= den != 0.0 && (den > 0.0) == (den0 > 0.0);
      if (den == 0.0) continue;
      const double mx = (p->h1[0] * d[k][0] + p->h1[1] * d[k][1] + p->h1[2]) / den;
      const double my = (p->h2[0] * d[k][0] + p->h2[1] * d[k][1] + p->h2[2]) / den;
      out[0] += mx > p->half_outer, out[1] += mx < -p->half_outer;
      out[2] += my > p->half_outer, out[3] += my < -p->half_outer;
    }
    // ... or the pixel lies wholly beyond one side of its outer square.
    const bool outside = same_sign && (out[0] == 4 || out[1] == 4 || out[2] == 4 || out[3] == 4);
    if (!behind && !outside) return false;
  }
  *hit = near != nullptr;
  if (near) {
    const bool inside =
        cell_col >= 0 && cell_row >= 0 && cell_col < near->bits.cols && cell_row < near->bits.rows;
    *grey =
        (near->c >= 0.0 || !inside || near->bits.ptr<uchar>(cell_row)[cell_col]) ? white : black;
  }
  return true;
}

// Seeded clutter: smooth gradients, soft blobs, ellipses and lines. Only
// round/elongated shapes are drawn so that no square with a dark border and
// a light surround is created on purpose; a detector pass then scrubs any
// accidental look-alike, which keeps false positives out of tests.
cv::Mat Background(cv::Size size, const RenderOptions& opt) {
  cv::Mat bg(size, CV_8UC3, cv::Scalar::all(128));
  if (!opt.textured_background) return bg;
  cv::RNG rng(opt.seed * 2654435761u + 12345u);
  auto colour = [&](int lo, int hi) {
    return cv::Scalar(rng.uniform(lo, hi), rng.uniform(lo, hi), rng.uniform(lo, hi));
  };
  // Low-frequency colour field: tiny random image upsampled smoothly.
  cv::Mat tiny(rng.uniform(3, 7), rng.uniform(3, 7), CV_8UC3);
  rng.fill(tiny, cv::RNG::UNIFORM, cv::Scalar::all(70), cv::Scalar::all(200));
  cv::resize(tiny, bg, size, 0, 0, cv::INTER_CUBIC);
  const int d = std::max(size.width, size.height);
  const int n_shapes = 25 + d / 40;
  for (int i = 0; i < n_shapes; ++i) {
    const cv::Point c(rng.uniform(0, size.width), rng.uniform(0, size.height));
    switch (rng.uniform(0, 3)) {
      case 0:
        cv::ellipse(bg, c, cv::Size(rng.uniform(4, d / 8 + 6), rng.uniform(4, d / 8 + 6)),
                    rng.uniform(0.0, 180.0), 0, 360, colour(40, 230), cv::FILLED, cv::LINE_AA);
        break;
      case 1:
        cv::line(bg, c, c + cv::Point(rng.uniform(-d / 4, d / 4), rng.uniform(-d / 4, d / 4)),
                 colour(30, 240), rng.uniform(1, 5), cv::LINE_AA);
        break;
      default:
        cv::circle(bg, c, rng.uniform(3, d / 12 + 4), colour(40, 230), rng.uniform(1, 4),
                   cv::LINE_AA);
    }
  }
  cv::Mat grain(size, CV_8UC3);
  rng.fill(grain, cv::RNG::NORMAL, cv::Scalar::all(0), cv::Scalar::all(6));
  cv::GaussianBlur(bg, bg, cv::Size(), 0.8);
  cv::add(bg, grain, bg, cv::noArray(), CV_8UC3);  // saturating, deterministic

  // Safety net against accidental marker look-alikes (permissive detector).
  auto params = cv::aruco::DetectorParameters::create();
  params->minMarkerPerimeterRate = 0.01;
  std::vector<std::vector<cv::Point2f>> corners;
  std::vector<int> ids;
  cv::Mat grey;
  cv::cvtColor(bg, grey, cv::COLOR_BGR2GRAY);
  cv::aruco::detectMarkers(grey, cv::aruco::getPredefinedDictionary(opt.dictionary), corners, ids,
                           params);
  for (const auto& q : corners) {
    const cv::Rect r =
        (cv::boundingRect(q) + cv::Size(8, 8) - cv::Point(4, 4)) & cv::Rect(cv::Point(0, 0), size);
    bg(r).setTo(cv::mean(bg(r)));
  }
  return bg;
}

// Centred linear motion-blur kernel: the segment is splatted bilinearly at
// fine steps so fractional lengths/angles work and the blur adds no shift.
cv::Mat MotionKernel(double length, double angle_deg) {
  const int half = static_cast<int>(std::ceil(length / 2)) + 1;
  cv::Mat k(2 * half + 1, 2 * half + 1, CV_64F, cv::Scalar(0));
  const double dx = std::cos(angle_deg * kDeg), dy = std::sin(angle_deg * kDeg);
  const int steps = std::max(2, static_cast<int>(length * 16));
  for (int i = 0; i <= steps; ++i) {
    const double t = length * (double(i) / steps - 0.5);
    const double x = half + t * dx, y = half + t * dy;
    const int ix = static_cast<int>(std::floor(x)), iy = static_cast<int>(std::floor(y));
    const double fx = x - ix, fy = y - iy;
    k.at<double>(iy, ix) += (1 - fx) * (1 - fy);
    k.at<double>(iy, ix + 1) += fx * (1 - fy);
    k.at<double>(iy + 1, ix) += (1 - fx) * fy;
    k.at<double>(iy + 1, ix + 1) += fx * fy;
  }
  return k / cv::sum(k)[0];
}

}  // namespace

Camera MakeCamera(cv::Size size, double hfov_deg) {
  const double f = 0.5 * size.width / std::tan(0.5 * hfov_deg * kDeg);
  return {
      cv::Matx33d(f, 0, 0.5 * (size.width - 1), 0, f, 0.5 * (size.height - 1), 0, 0, 1), {}, size};
}

Camera MakeFisheyeCamera(cv::Size size, double hfov_deg, const std::vector<double>& k) {
  CV_Assert(k.size() == 4 && hfov_deg > 0 && hfov_deg < 180);
  const double t = 0.5 * hfov_deg * kDeg, t2 = t * t;
  const double theta_d = t * (1 + t2 * (k[0] + t2 * (k[1] + t2 * (k[2] + t2 * k[3]))));
  const double f = 0.5 * size.width / theta_d;
  Camera cam{cv::Matx33d(f, 0, 0.5 * (size.width - 1), 0, f, 0.5 * (size.height - 1), 0, 0, 1), k,
             size};
  cam.fisheye = true;
  return cam;
}

std::array<cv::Point3d, 4> MarkerCorners3d(double side) {
  const double h = side / 2;
  return {cv::Point3d(-h, h, 0), cv::Point3d(h, h, 0), cv::Point3d(h, -h, 0),
          cv::Point3d(-h, -h, 0)};
}

std::array<cv::Point2f, 4> ProjectCorners(const Camera& cam, const Marker& m) {
  const auto obj = MarkerCorners3d(m.side);
  const std::vector<cv::Point2d> img =
      Project(cam, std::vector<cv::Point3d>(obj.begin(), obj.end()), m.rvec, m.tvec);
  return {cv::Point2f(img[0]), cv::Point2f(img[1]), cv::Point2f(img[2]), cv::Point2f(img[3])};
}

cv::Point2f ProjectCentre(const Camera& cam, const Marker& m) {
  return cv::Point2f(Project(cam, {{0, 0, 0}}, m.rvec, m.tvec)[0]);
}

cv::Mat RenderScene(const Camera& cam, const std::vector<Marker>& markers, const RenderOptions& opt,
                    cv::Mat* depth) {
  CV_Assert(cam.size.area() > 0 && opt.supersample >= 1);
  cv::Mat img;
  Background(cam.size, opt).convertTo(img, CV_32FC3);
  cv::Mat z(cam.size, CV_32F, cv::Scalar(opt.background_depth));

  const auto dict = cv::aruco::getPredefinedDictionary(opt.dictionary);
  std::vector<PreparedMarker> prep;
  for (const Marker& m : markers) {
    CV_Assert(m.id >= 0 && m.id < dict->bytesList.rows && m.side > 0);
    cv::Mat bits;  // one pixel per cell, border included
    cv::aruco::drawMarker(dict, m.id, dict->markerSize + 2, bits, 1);
    prep.push_back(Prepare(cam, m, bits, opt.quiet_zone));
    if (prep.back().box.empty()) prep.pop_back();
  }

  if (!prep.empty()) {
    cv::Rect all = prep[0].box;
    for (const auto& p : prep) all |= p.box;
    const RayMap rays(cam, all);
    const int n2 = opt.supersample * opt.supersample;
    const double inv_n2 = 1.0 / n2;
    const int gen = Rank1Generator(n2);
    cv::parallel_for_(cv::Range(all.y, all.y + all.height), [&](const cv::Range& range) {
      std::vector<const PreparedMarker*> in_row, cand;
      for (int v = range.start; v < range.end; ++v) {
        auto* row = img.ptr<cv::Vec3f>(v);
        auto* zrow = z.ptr<float>(v);
        in_row.clear();
        for (const auto& p : prep)
          if (v >= p.box.y && v < p.box.y + p.box.height) in_row.push_back(&p);
        for (int u = all.x; u < all.x + all.width; ++u) {
          cand.clear();
          for (const PreparedMarker* p : in_row)
            if (u >= p->box.x && u < p->box.x + p->box.width) cand.push_back(p);
          if (cand.empty()) continue;
          double g = 0, zz = 0;
          const cv::Vec2d corner[4] = {rays(u - 0.5, v - 0.5), rays(u + 0.5, v - 0.5),
                                       rays(u + 0.5, v + 0.5), rays(u - 0.5, v + 0.5)};
          bool hit = false;
          if (UniformPixel(cand, corner, opt.background_depth, opt.white_level, opt.black_level,
                           &hit, &g)) {
            if (hit) row[u] = cv::Vec3f::all(static_cast<float>(g));
          } else {
            // Rank-1 lattice, Cranley-Patterson shifted per pixel (see Rank1Generator).
            double sum = 0;
            int misses = 0;
            const double sx = n2 > 1 ? PixelHash(u, v, 0) : 0.5,
                         sy = n2 > 1 ? PixelHash(u, v, 1) : 0.5;
            for (int k = 0, ky = 0; k < n2; ++k, ky = ky + gen < n2 ? ky + gen : ky + gen - n2) {
              const double fx = k * inv_n2 + sx, fy = ky * inv_n2 + sy;
              const cv::Vec2d r =
                  rays(u - 0.5 + (fx - std::floor(fx)), v - 0.5 + (fy - std::floor(fy)));
              if (CastRay(cand, r[0], r[1], opt.background_depth, opt.white_level, opt.black_level,
                          &g, &zz))
                sum += g;
              else
                ++misses;
            }
            // Misses keep the background colour; hits are achromatic ink/paper.
            row[u] = row[u] * static_cast<float>(misses * inv_n2) +
                     cv::Vec3f::all(static_cast<float>(sum * inv_n2));
          }
          const cv::Vec2d rc = rays(u, v);
          CastRay(cand, rc[0], rc[1], opt.background_depth, 0, 0, &g, &zz);
          zrow[u] = static_cast<float>(zz);
        }
      }
    });
  }

  // Photometric degradations act on the finished optical image, in float so
  // rounding happens once.
  if (!opt.colour) cv::cvtColor(img, img, cv::COLOR_BGR2GRAY);
  img = ((img - cv::Scalar::all(128)) * opt.contrast + cv::Scalar::all(128)) * opt.brightness;
  if (opt.blur_sigma > 0) cv::GaussianBlur(img, img, cv::Size(), opt.blur_sigma);
  if (opt.motion_blur_px > 0)
    cv::filter2D(img, img, -1, MotionKernel(opt.motion_blur_px, opt.motion_blur_angle_deg),
                 cv::Point(-1, -1), 0, cv::BORDER_REFLECT);
  if (opt.noise_sigma > 0) {
    cv::Mat noise(img.size(), img.type());
    cv::RNG rng(opt.seed * 747796405u + 2891336453u);
    rng.fill(noise, cv::RNG::NORMAL, cv::Scalar::all(0), cv::Scalar::all(opt.noise_sigma));
    img += noise;
  }
  cv::Mat out;
  img.convertTo(out, opt.colour ? CV_8UC3 : CV_8UC1);  // rounds and saturates
  if (depth) *depth = z;
  return out;
}

DepthNoise::DepthNoise(double baseline_m, double disparity_sigma_px, double correlation,
                       double edge_fattening, double texture)
    : baseline(baseline_m),
      disparity_sigma(disparity_sigma_px),
      correlation_px(correlation),
      edge_fattening_px(edge_fattening),
      min_texture(texture) {}

// Stereolabs' ZED 2 datasheet gives a 120 mm baseline and depth accuracy "< 1% up to 3 m, < 5% up
// to 15 m". With its HD720 focal length (110 deg wide over 1280 px, f ~ 450 px) both bounds work out
// to sigma_d ~ 0.18 px; as they are upper bounds, 0.15 px is taken (block matching is 0.1-0.3 px).
// Passive stereo: no projector, so featureless patches give no depth. The correlation length and
// fattening stand for SGM's smoothing and half a matching window; no published figure.
DepthNoise DepthNoise::Zed2() { return DepthNoise(0.12, 0.15, 5.0, 3.0, 1.5); }

// Intel's D400 tuning white paper ("Best-Known-Methods for Tuning Intel RealSense D400 Depth
// Cameras") writes depth RMS error = z^2 * subpixel / (f * B) with a subpixel RMS of about 0.08 px
// on a well-textured target (0.1 at worst); the D435 baseline is 50 mm. Scenes are rarely that well
// textured, so 0.10 px is taken (the bottom of block matching's 0.1-0.3 px). Its IR projector
// textures blank surfaces, so no textureless holes.
DepthNoise DepthNoise::D435() { return DepthNoise(0.050, 0.10, 3.0, 2.0, 0.0); }

double DepthNoise::SigmaZ(double z, double focal_px) const {
  return baseline > 0 ? z * z * disparity_sigma / (focal_px * baseline) : 0.0;
}

namespace {

// Unit-variance Gaussian field of `size`, blurred with a Gaussian of `sigma` px (white when 0) and
// rescaled so that every pixel's standard deviation is 1 again. It is drawn on a canvas padded by
// the kernel's reach, so pixels at the border average as many draws as those in the middle.
cv::Mat CorrelatedField(cv::Size size, double sigma, cv::RNG& rng) {
  const int reach = sigma > 0 ? static_cast<int>(std::ceil(3.0 * sigma)) : 0;
  cv::Mat canvas(size.height + 2 * reach, size.width + 2 * reach, CV_32F);
  rng.fill(canvas, cv::RNG::NORMAL, cv::Scalar(0), cv::Scalar(1));
  if (reach == 0) return canvas;
  const cv::Mat k = cv::getGaussianKernel(2 * reach + 1, sigma, CV_64F);
  // Separable kernel k k^T: the blurred variance is sum((k k^T)^2) = (sum k^2)^2.
  const double gain = k.dot(k);
  cv::Mat blurred;
  cv::sepFilter2D(canvas, blurred, CV_32F, k, k, cv::Point(-1, -1), 0, cv::BORDER_REPLICATE);
  return blurred(cv::Rect(reach, reach, size.width, size.height)) / gain;
}

// Grey-level standard deviation over a 7x7 window around each pixel (CV_32F).
cv::Mat LocalContrast(const cv::Mat& image) {
  cv::Mat grey, mean, sq;
  if (image.channels() == 3)
    cv::cvtColor(image, grey, cv::COLOR_BGR2GRAY);
  else
    grey = image;
  grey.convertTo(grey, CV_32F);
  cv::boxFilter(grey, mean, CV_32F, cv::Size(7, 7), cv::Point(-1, -1), true, cv::BORDER_REFLECT);
  cv::boxFilter(grey.mul(grey), sq, CV_32F, cv::Size(7, 7), cv::Point(-1, -1), true,
                cv::BORDER_REFLECT);
  cv::Mat var = cv::max(sq - mean.mul(mean), 0.0);
  cv::sqrt(var, var);
  return var;
}

}  // namespace

cv::Mat MakeOrganizedCloud(const Camera& cam, const cv::Mat& depth, const CloudOptions& opt,
                           const cv::Mat& image) {
  CV_Assert(depth.type() == CV_32F && depth.size() == cam.size);
  CV_Assert(image.empty() || image.size() == cam.size);
  const DepthNoise& stereo = opt.stereo;
  CV_Assert(stereo.baseline >= 0 && stereo.disparity_sigma >= 0 && stereo.correlation_px >= 0 &&
            stereo.edge_fattening_px >= 0);
  const RayMap rays(cam, cv::Rect(cv::Point(0, 0), cam.size));
  cv::RNG rng(opt.seed);
  cv::Mat noise(depth.size(), CV_64F, cv::Scalar(0));
  if (opt.depth_noise_sigma > 0)
    rng.fill(noise, cv::RNG::NORMAL, cv::Scalar(0), cv::Scalar(opt.depth_noise_sigma));

  // Stereo happens in disparity, d = f B / z (0 = no match). Its own generator keeps the draws
  // above, and so clouds made without a stereo model, as they were.
  const bool has_stereo = stereo.baseline > 0;
  const double fb = cam.K(0, 0) * stereo.baseline;
  cv::Mat disparity(depth.size(), CV_32F, cv::Scalar(0));
  if (has_stereo) {
    for (int v = 0; v < depth.rows; ++v)
      for (int u = 0; u < depth.cols; ++u) {
        const float d = depth.at<float>(v, u);
        if (std::isfinite(d) && d > 0) disparity.at<float>(v, u) = static_cast<float>(fb / d);
      }
    if (stereo.edge_fattening_px > 0) {
      // A pixel within the fattening radius of a nearer surface (a disparity larger by more than
      // the edge threshold) takes that surface's disparity, as a matching window straddling the
      // edge locks onto the foreground; no-depth pixels count as infinitely far.
      const int r = std::max(1, static_cast<int>(std::lround(stereo.edge_fattening_px)));
      cv::Mat nearest;
      cv::dilate(disparity, nearest,
                 cv::getStructuringElement(cv::MORPH_ELLIPSE, cv::Size(2 * r + 1, 2 * r + 1)));
      const cv::Mat edge = nearest - disparity > stereo.edge_jump_px;
      nearest.copyTo(disparity, edge);
    }
    if (stereo.disparity_sigma > 0) {
      cv::RNG stereo_rng(opt.seed * 2246822519u + 3266489917u);
      const cv::Mat field = CorrelatedField(depth.size(), stereo.correlation_px, stereo_rng);
      cv::Mat valid = disparity > 0;
      disparity += field * stereo.disparity_sigma;
      disparity.setTo(0, ~valid);
    }
  }

  // Holes: a blurred random field thresholded at its quantile makes stereo-like
  // clustered dropouts of 70 % of the requested share; salt outside the blobs makes the rest.
  cv::Mat hole(depth.size(), CV_8U, cv::Scalar(0));
  if (opt.nan_fraction > 0) {
    const double blob_share = opt.hole_blobs ? 0.7 : 0.0;
    if (blob_share > 0) {
      cv::Mat field(depth.size(), CV_32F);
      rng.fill(field, cv::RNG::UNIFORM, cv::Scalar(0), cv::Scalar(1));
      cv::GaussianBlur(field, field, cv::Size(), 6.0);
      std::vector<float> vals(field.begin<float>(), field.end<float>());
      const size_t k =
          std::min(vals.size() - 1,
                   static_cast<size_t>(vals.size() * (1.0 - blob_share * opt.nan_fraction)));
      std::nth_element(vals.begin(), vals.begin() + k, vals.end());
      hole = field > vals[k];
    }
    cv::Mat salt(depth.size(), CV_32F);
    rng.fill(salt, cv::RNG::UNIFORM, cv::Scalar(0), cv::Scalar(1));
    const double blobs = blob_share * opt.nan_fraction;
    hole |= salt < std::min(1.0, (opt.nan_fraction - blobs) / (1.0 - blobs));
  }
  if (has_stereo && stereo.min_texture > 0 && !image.empty())
    hole |= LocalContrast(image) < stereo.min_texture;

  const float nan = std::numeric_limits<float>::quiet_NaN();
  cv::Mat cloud(depth.size(), CV_32FC3);
  for (int v = 0; v < depth.rows; ++v)
    for (int u = 0; u < depth.cols; ++u) {
      double d = depth.at<float>(v, u);
      if (has_stereo) {
        const double disp = disparity.at<float>(v, u);
        d = disp > 0 ? fb / disp : nan;  // a match pushed past infinity is no match
      }
      if (hole.at<uchar>(v, u) || !std::isfinite(d) || d <= 0) {
        cloud.at<cv::Vec3f>(v, u) = cv::Vec3f(nan, nan, nan);
        continue;
      }
      const cv::Vec2d r = rays(u, v);
      const double zn = d * (1.0 + noise.at<double>(v, u));  // along the ray: x, y scale too
      cloud.at<cv::Vec3f>(v, u) = cv::Vec3f(static_cast<float>(r[0] * zn),
                                            static_cast<float>(r[1] * zn), static_cast<float>(zn));
    }
  return cloud;
}

Marker FacingCamera(int id, double side, cv::Vec3d position, double yaw_deg, double pitch_deg,
                    double roll_deg) {
  // Facing: marker x -> camera x, marker y -> camera -y (up), marker z -> camera -z.
  const cv::Matx33d facing(1, 0, 0, 0, -1, 0, 0, 0, -1);
  const double y = yaw_deg * kDeg, p = pitch_deg * kDeg, r = roll_deg * kDeg;
  const cv::Matx33d ry(std::cos(y), 0, std::sin(y), 0, 1, 0, -std::sin(y), 0, std::cos(y));
  const cv::Matx33d rx(1, 0, 0, 0, std::cos(p), -std::sin(p), 0, std::sin(p), std::cos(p));
  const cv::Matx33d rz(std::cos(r), -std::sin(r), 0, std::sin(r), std::cos(r), 0, 0, 0, 1);
  Marker m;
  m.id = id;
  m.side = side;
  cv::Rodrigues(facing * ry * rx * rz, m.rvec);
  m.tvec = position;
  return m;
}

Marker FacingRay(int id, double side, cv::Vec3d position, double tilt_deg, double tilt_axis_deg,
                 double roll_deg) {
  // Base frame: z towards the camera along the ray, x as close to image right
  // as possible, y = z x x (up-ish), so tilt 0 means squarely viewed.
  const cv::Vec3d z = -cv::normalize(position);
  cv::Vec3d x = cv::Vec3d(1, 0, 0) - z[0] * z;
  x = cv::norm(x) > 1e-9 ? cv::normalize(x) : cv::Vec3d(0, 1, 0);
  const cv::Vec3d y = z.cross(x);
  const cv::Matx33d base(x[0], y[0], z[0], x[1], y[1], z[1], x[2], y[2], z[2]);
  cv::Matx33d tilt, roll;
  const double a = tilt_axis_deg * kDeg;
  cv::Rodrigues(cv::Vec3d(std::cos(a), std::sin(a), 0) * (tilt_deg * kDeg), tilt);
  cv::Rodrigues(cv::Vec3d(0, 0, roll_deg * kDeg), roll);
  Marker m;
  m.id = id;
  m.side = side;
  cv::Rodrigues(base * tilt * roll, m.rvec);
  m.tvec = position;
  return m;
}

Marker RandomMarker(cv::RNG& rng, const Camera& cam, int id, double side, double min_range,
                    double max_range, double max_tilt_deg) {
  for (int attempt = 0; attempt < 200; ++attempt) {
    const double zc = rng.uniform(min_range, max_range);
    const double u = rng.uniform(0.0, double(cam.size.width));
    const double v = rng.uniform(0.0, double(cam.size.height));
    // K alone spreads a pinhole camera's markers well enough (and keeps the scenes the tests were
    // tuned on); a fisheye's K would crowd them into the middle third of the image.
    cv::Vec3d ray = cam.K.inv() * cv::Vec3d(u, v, 1.0);
    if (cam.fisheye) {
      cv::Mat xy;
      Undistort(cam, cv::Mat(std::vector<cv::Point2d>{{u, v}}), xy);
      ray = cv::Vec3d(xy.at<cv::Point2d>(0).x, xy.at<cv::Point2d>(0).y, 1.0);
    }
    // Uniform in angle, not solid angle, so strong obliques are well represented.
    const double tilt = rng.uniform(0.0, max_tilt_deg), axis = rng.uniform(0.0, 360.0);
    const Marker m = FacingRay(id, side, ray * zc, tilt, axis, rng.uniform(0.0, 360.0));
    Marker big = m;
    big.side = side * 1.5;
    cv::Matx33d r;
    cv::Rodrigues(m.rvec, r);
    bool ok = true;
    for (const auto& c : MarkerCorners3d(big.side))
      ok &= (r * cv::Vec3d(c.x, c.y, c.z) + m.tvec)[2] > 0.05;
    if (!ok) continue;
    for (const auto& p : ProjectCorners(cam, big))
      ok &= p.x >= 2 && p.y >= 2 && p.x <= cam.size.width - 3 && p.y <= cam.size.height - 3;
    if (ok) return m;
  }
  return FacingCamera(id, side, cv::Vec3d(0, 0, 0.5 * (min_range + max_range)));
}

cv::Mat MarkerPlanesCloud(const cv::Matx33d& K, const std::vector<double>& D, cv::Size image_size, int factor,
                          const std::vector<Marker>& markers, double wall_depth) {
  const cv::Size size(image_size.width / factor, image_size.height / factor);
  std::vector<cv::Point2f> pixels, rays;
  for (int v = 0; v < size.height; ++v)
    for (int u = 0; u < size.width; ++u) pixels.emplace_back((u + 0.5f) * factor - 0.5f, (v + 0.5f) * factor - 0.5f);
  cv::undistortPoints(pixels, rays, K, D);
  std::vector<cv::Matx33d> rotations;
  for (const auto& m : markers) {
    rotations.emplace_back();
    cv::Rodrigues(m.rvec, rotations.back());
  }
  cv::Mat points(size, CV_32FC3);
  for (int i = 0; i < static_cast<int>(rays.size()); ++i) {
    const cv::Vec3d ray(rays[i].x, rays[i].y, 1.0);
    cv::Vec3d point = ray * wall_depth;
    for (size_t k = 0; k < markers.size(); ++k) {
      const cv::Matx33d& r = rotations[k];
      const cv::Vec3d normal(r(0, 2), r(1, 2), r(2, 2));
      const cv::Vec3d hit = ray * (normal.dot(markers[k].tvec) / normal.dot(ray));
      const cv::Vec3d local = r.t() * (hit - markers[k].tvec);
      if (std::abs(local[0]) < 0.7 * markers[k].side && std::abs(local[1]) < 0.7 * markers[k].side) point = hit;
    }
    points.at<cv::Vec3f>(i / size.width, i % size.width) = cv::Vec3f(point);
  }
  return points;
}

}  // namespace arucotag::sim

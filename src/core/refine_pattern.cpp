// Corner refinement by fitting the decoded marker's whole black-and-white pattern to the image.
//
// The edge fit (refine_edges.cpp) sees only the outer border next to each corner. A marker 15-40 px
// wide has few pixels there, and its pose (tilt, and which of the two planar poses is right) hangs
// on differences of a few thousandths of a pixel between its sides. Every cell boundary inside the
// marker is also known once the id is: this fits the four corners (the homography they define) so
// that the exact pixel-area coverage of the black cells, blurred by a Gaussian of fitted width (the
// lens), times a contrast plus a brightness and a brightness gradient, matches the grey values of
// all pixels of the marker and a strip of its quiet zone (Gauss-Newton with Levenberg damping and
// Huber weights). Coverage and its derivatives are exact: the edges of each projected run of black
// cells are walked through the pixels they cross, each piece adding its signed area to its row
// (summed from the left, the covered area of every pixel), and moving a cell edge changes the
// covered area by the length of that edge inside the pixel. Without the blur term a camera's 0.5-1 px
// blur pulls thin cells' edges apart and the fit ends up worse than the edge fit it starts from.
#include <arucotag/refine.hpp>

#include "geometry.hpp"
#include "refine_pattern.hpp"

#include <algorithm>
#include <cmath>
#include <cstring>
#include <iterator>
#include <limits>
#include <numeric>
#include <type_traits>
#include <vector>

#include <opencv2/core/hal/hal.hpp>

namespace arucotag {

namespace {

using Vec2 = cv::Point2d;

// 8 corner coordinates, brightness, contrast, brightness gradient x and y, blur variance (px^2).
constexpr int kParams = 13;
constexpr int kBlur = 12;
// Blur variance range: up to sigma 1.5 px (blurrier markers are not worth a sharper fit), and the
// kernel radius that range needs.
constexpr double kMaxBlurVariance = 2.25;
constexpr int kBlurRadius = 5;
// Blur variances (px^2) tried for the start: sharp, sigma 0.3, 0.5, 0.8 and 1.2 px. The kernel's hat
// (BlurKernel) adds a variance of its own, from 0 at 0 to 1/6 px^2 (0.14-0.15 at 0.07-0.1), so a lens
// blur of sigma 0.5 px fits at about 0.07-0.1 px^2, not 0.25.
// Without 0.09 such markers started at 0.25, and the first Gauss-Newton step took the variance to
// 0-0.008, where the cost was up to 2.4 times the start's (near 0 it rises with the kernel's sigma, not its
// variance: the linear model overshoots): the step was refused and the fit paid for one more trial. On
// 640x480 frames of 20 markers 18 of 44 first trials were refused, of 50 markers 15 of 54; with 0.09
// none, and 28 and 39 trials in all. Callgrind of Detect: 640x480 with 20 markers 76.9 -> 74.0 M, with
// 50 113.6 -> 111.3 M, tag36h11 at 720p 94.9 -> 93.2 M; the real 640x480 photos 56.5 -> 57.1 M (their
// sharp prints try one blur more), the dim distant set 115.5 -> 115.6 M. The corners' median error on
// the 20 markers 0.0140 -> 0.0127 px, on tag36h11 at 720p 0.0149 -> 0.0129 px, p95 the same.
constexpr double kStartBlurVariances[] = {0.0, 0.09, 0.25, 0.64, 1.44};
// px: edge-refined corners of markers under 20 px, seen at 60 degrees, start up to 1.3 px off.
constexpr double kMaxMove = 2.0;
// px: cells at least this wide are sampled on every other pixel (see SelectPixels).
constexpr double kCheckerboardCell = 4.0;
// Pixels a fit samples at most, about the checkerboard of a 95 px marker: larger ones are sampled on
// a sparser lattice (see SelectPixels), so the fit's per-sample work (most of it) stops growing with
// the square of the side. Measured on blurred (0.8 px), noisy (3 grey levels) renders of 96-256 px
// markers, tilted 0-50 degrees: corners within 0.023 px of the truth (0.0095-0.014 px with every
// pixel; the edge fit alone 0.054-0.075 px; test_refine_pattern).
constexpr double kMaxSamples = 6000.0;
// px: larger markers are refused: the per-thread coverage buffers grow with the square of the side
// (a few MB at this size).
constexpr double kMaxSide = 256.0;
constexpr int kMaxIterations = 20;
// px: a rejected step smaller than this ends the fit (the cost no longer tells such steps apart).
constexpr double kNoiseFloorStep = 0.01;
// Share of pixels the fitted pattern may miss by over a quarter of its contrast. Measured: 0-0.3 %
// on rendered markers (sharp, blurred, noisy) and on the printed markers of the OpenCV tutorial
// photo; 16-20 % with another id's pattern; 50 % half occluded; 8-15 % on the ChArUco photo, whose
// print bleeds (white cells come out as rounded blobs), where the edge fit is kept.
constexpr double kMaxOutliers = 0.05;
// Share of pixels a fit's start may miss before its trial steps are costed ahead of their normal
// equations (FitPattern). On the bench sets' cold fits: the 16 refused on the bleeding ChArUco prints of
// the photos started at 0.11-0.20 and were refused after their first trial step, whose normal equations
// were then wasted; of the accepted ones, which pay for that cost once more, 15 of 95 on the distant
// tag36h11 set, 7 of 41 on the dim one, 3 of 42 at 720p and none of 15 on 640x480 with five markers started
// at 0.1 or more. Callgrind of Detect: the photos 71.3 -> 68.8 M, the distant and dim sets +0.1 M.
constexpr double kDoubtfulOutliers = 0.1;
constexpr double kConverged = 1e-3;  // px: smaller steps changed corners by < 0.001 px (measured)

double Cross(const Vec2& a, const Vec2& b) { return a.x * b.y - a.y * b.x; }

// Walks the segment from a to b through the pixels it crosses, in plane coordinates (pixel column i
// is [i, i + 1), row j [j, j + 1)): visit(i, j, t0, t1) for each piece of it inside one pixel, t the
// segment's parameter (0 at a, 1 at b), in order. A line enters a pixel once, so each pixel gets
// one piece.
template <typename Visit>
ARUCOTAG_INLINE void WalkSegment(const Vec2& a, const Vec2& b, const Visit& visit) {
  const Vec2 d = b - a;
  int ix = static_cast<int>(std::floor(a.x)), iy = static_cast<int>(std::floor(a.y));
  const int step_x = d.x > 0 ? 1 : -1, step_y = d.y > 0 ? 1 : -1;
  constexpr double kNever = std::numeric_limits<double>::infinity();
  // Where the segment next crosses a column boundary and a row boundary, and the parameter per
  // column and per row.
  double next_x = d.x != 0.0 ? ((d.x > 0 ? ix + 1 : ix) - a.x) / d.x : kNever;
  double next_y = d.y != 0.0 ? ((d.y > 0 ? iy + 1 : iy) - a.y) / d.y : kNever;
  const double per_x = d.x != 0.0 ? 1.0 / std::abs(d.x) : kNever, per_y = d.y != 0.0 ? 1.0 / std::abs(d.y) : kNever;
  // The pixels between the ends (and two for round-off at a pixel corner): a bound on the steps.
  const int pixels =
      std::abs(static_cast<int>(std::floor(b.x)) - ix) + std::abs(static_cast<int>(std::floor(b.y)) - iy);
  double t0 = 0.0;
  for (int step = 0; step <= pixels + 2 && t0 < 1.0; ++step) {
    const double t1 = std::min({next_x, next_y, 1.0});
    if (t1 > t0) visit(ix, iy, t0, t1);
    t0 = t1;
    if (next_x <= next_y) {
      ix += step_x;
      next_x += per_x;
    } else {
      iy += step_y;
      next_y += per_y;
    }
  }
}

// +1 when the polygon's shoelace area is positive (in image coordinates), else -1.
double Orientation(const Vec2* polygon, size_t count) {
  double shoelace = 0.0;
  for (size_t i = 0; i < count; ++i) shoelace += Cross(polygon[i], polygon[(i + 1) % count]);
  return shoelace >= 0 ? 1.0 : -1.0;
}

// One edge, from a to b, of a polygon of orientation s (Orientation), in plane coordinates (see
// WalkSegment) of a plane `width` x `height`: each piece inside a pixel adds its signed area to the
// row's steps in `steps` (rows of width + 1: what the rightmost column passes on), whose sum from the
// left (SumRows) is each pixel's covered area once every edge is added (the trapezoids of a closed
// polygon's edges add up to its area; an edge two polygons share cancels). A piece left of the plane
// passes its whole height on. The pieces on pixels of the plane then go to
// on_piece(x, y, t0, t1).
template <typename OnPiece>
ARUCOTAG_INLINE void AddEdgeArea(const Vec2& a, const Vec2& b, double s, int width, int height, double* steps,
                                 const OnPiece& on_piece) {
  const Vec2 d = b - a;
  WalkSegment(a, b, [&](int ix, int iy, double t0, double t1) {
    if (iy < 0 || iy >= height || ix >= width) return;  // no pixel of the plane right of it
    double* row = steps + static_cast<size_t>(iy) * (width + 1);
    const double rise = -s * (t1 - t0) * d.y;
    if (ix < 0) {
      row[0] += rise;
      return;
    }
    const double middle = 0.5 * ((a.x + t0 * d.x) + (a.x + t1 * d.x)) - ix;
    row[ix] += rise * (1.0 - middle);
    row[ix + 1] += rise * middle;
    on_piece(ix, iy, t0, t1);
  });
}

// Each row of `steps` (AddEdgeArea's) summed from the left into the `width` x `height` plane `out`.
template <typename T>
void SumRows(const double* steps, int width, int height, T* out) {
  for (int y = 0; y < height; ++y) {
    const double* row = steps + static_cast<size_t>(y) * (width + 1);
    T* covered = out + static_cast<size_t>(y) * width;
    double sum = 0.0;
    for (int x = 0; x < width; ++x) {
      sum += row[x];
      covered[x] = static_cast<T>(sum);
    }
  }
}

// Homography taking grid coordinates (u, v) in [0, cells]^2 to the image, with the grid's corners
// (0, 0), (cells, 0), (cells, cells), (0, cells) at corners[0..3].
cv::Matx33d GridToImage(const std::array<Vec2, 4>& corners, int cells) {
  const double k = 1.0 / cells;
  return internal::SquareToQuad(corners) * cv::Matx33d(k, 0, 0, 0, k, 0, 0, 0, 1);
}

struct Sample {
  int x, y;
  double grey;
};

// The first n elements of a scratch buffer reused from fit to fit: it grows and never shrinks, so a
// fit on a bigger marker than the last does not value-initialise again the tail a shrink dropped.
// std::vector's resize and assign did, one float at a time (3.5 % of the drive-by's instructions in
// video mode). The contents are whatever the last user left.
template <class T>
T* Buffer(std::vector<T>& buffer, size_t n) {
  if (buffer.size() < n) buffer.resize(n);
  return buffer.data();
}

// The same, zeroed.
template <class T>
T* ZeroedBuffer(std::vector<T>& buffer, size_t n) {
  static_assert(std::is_trivially_copyable<T>::value, "zeroed bytewise");
  return static_cast<T*>(std::memset(Buffer(buffer, n), 0, n * sizeof(T)));
}

// Blur kernel acting on pixel-area coverages: the Gaussian of the given variance applied to the
// piecewise-linear interpolation of the coverage samples, i.e. taps K(k) = E[tri(k - s)] with s
// Gaussian and tri the unit hat. Unlike the sampled Gaussian it is exact at variance 0 ([0 1 0]) and
// stays right for sub-pixel blur, where the sampled
// Gaussian's shape error grows. Radius 3.5 sigma + 1, at most kBlurRadius.
struct Kernel {
  int radius = 0;
  std::array<double, 2 * kBlurRadius + 1> taps{};
  double at(int k) const { return taps[k + kBlurRadius]; }
};

Kernel BlurKernel(double variance) {
  Kernel kernel;
  const double sigma = std::sqrt(std::max(variance, 0.0));
  kernel.radius = std::min(kBlurRadius, static_cast<int>(std::ceil(3.5 * sigma)) + 1);
  // ramp(a) = E[(a - s)+] for s ~ N(0, sigma^2); tri(t) = ramp(t+1) - 2 ramp(t) + ramp(t-1).
  const auto ramp = [sigma](double a) {
    if (sigma < 1e-9) return std::max(a, 0.0);
    const double z = a / sigma;
    return a * 0.5 * std::erfc(-z / std::sqrt(2.0)) + sigma * std::exp(-0.5 * z * z) / std::sqrt(2.0 * M_PI);
  };
  // Each tap takes the ramp at three neighbouring integers: every ramp value is made once (the same
  // arguments, so the same taps; the error function and exponential were most of a kernel's cost).
  std::array<double, 2 * kBlurRadius + 3> ramps;
  for (int k = -kernel.radius - 1; k <= kernel.radius + 1; ++k) ramps[k + kBlurRadius + 1] = ramp(k);
  const auto ramp_at = [&ramps](int k) { return ramps[k + kBlurRadius + 1]; };
  double sum = 0.0;
  for (int k = -kernel.radius; k <= kernel.radius; ++k) {
    const double w = ramp_at(k + 1) - 2.0 * ramp_at(k) + ramp_at(k - 1);
    kernel.taps[k + kBlurRadius] = w;
    sum += w;
  }
  for (double& w : kernel.taps) w /= sum;
  return kernel;
}

// BlurKernel(variance), the start's variances (kStartBlurVariances, tried by every cold fit) computed
// once.
Kernel KernelFor(double variance) {
  static const std::array<Kernel, std::size(kStartBlurVariances)> start = [] {
    std::array<Kernel, std::size(kStartBlurVariances)> kernels;
    for (size_t v = 0; v < kernels.size(); ++v) kernels[v] = BlurKernel(kStartBlurVariances[v]);
    return kernels;
  }();
  for (size_t v = 0; v < start.size(); ++v) {
    if (variance == kStartBlurVariances[v]) return start[v];
  }
  return BlurKernel(variance);
}

// out[x] = sum over k in [-R, R] of tap[k] * in[x + k * stride], x in [0, count): each output is
// summed in a register, the taps in order (the same sum as adding tap by tap into `out`, in a
// quarter of the loads and stores). Inlined into Blurred, so it is built for each of its clones.
template <int R>
ARUCOTAG_INLINE void Convolve(const float* __restrict in, ptrdiff_t stride, const float* __restrict tap,
                              float* __restrict out, int count) {
  for (int x = 0; x < count; ++x) {
    float sum = 0.0f;
    for (int k = -R; k <= R; ++k) sum += tap[k] * in[x + k * stride];
    out[x] = sum;
  }
}

// A pixel's eight corner derivatives as one value: one AVX register, two SSE ones (GCC's and
// Clang's vector extension; loads and stores through memcpy, which makes no alignment claim).
typedef float SlopeVector __attribute__((vector_size(8 * sizeof(float))));
// (By reference: a vector returned by value would make the build without AVX warn about the ABI.)
ARUCOTAG_INLINE void LoadSlopes(const float* p, SlopeVector& v) { std::memcpy(&v, p, sizeof v); }
ARUCOTAG_INLINE void StoreSlopes(float* p, const SlopeVector& v) { std::memcpy(p, &v, sizeof v); }

class PatternFit {
 public:
  // Corner derivatives per pixel (8 floats: one SlopeVector).
  static constexpr int kSlopes = 8;
  static_assert(sizeof(SlopeVector) == kSlopes * sizeof(float), "one vector per pixel");

  PatternFit(const cv::Mat& grey, const cv::Mat& black, int cells, const std::array<Vec2, 4>& corners)
      : grey_(grey), black_(black), cells_(cells) {
    for (const Vec2& c : corners) origin_ += c * 0.25;
    samples_.clear();
    SelectPixels(corners);
  }

  size_t size() const { return samples_.size(); }
  // Whether the last Cover's corners keep the marker's grid near the coverage plane (else Cover left
  // the plane as it was and the corners are not to be evaluated).
  bool valid() const { return valid_; }
  // Area (px) of the marker and its quiet-zone strip: about the sample count when all of it is in
  // the image.
  double area() const { return area_; }
  const std::vector<Sample>& samples() const { return samples_; }
  const Vec2& origin() const { return origin_; }

  // Exact black coverage of every coverage pixel and its derivatives for the corners; then
  // Blurred() reads it at the samples.
  void Cover(const std::array<Vec2, 4>& corners) {
    if (covered_ && corners == covered_corners_) return;  // the start is covered twice otherwise
    covered_ = true;
    blurred_ = false;
    covered_corners_ = corners;
    const int n = cells_ + 1;
    // The (cells+1)^2 grid vertices from the homography of the corners relative to `origin_` (keeps
    // float round-off out), and their derivatives: the homography's by central differences, carried
    // to each vertex analytically (d p = (dH x - p dH_2 x) / w).
    vertices_.resize(static_cast<size_t>(n * n));
    Buffer(vertex_jac_, vertices_.size() * 16);  // every entry written below
    constexpr double kStep = 1e-4;
    std::array<Vec2, 4> local;
    for (int i = 0; i < 4; ++i) local[i] = corners[i] - origin_;
    const cv::Matx33d h = GridToImage(local, cells_);
    cv::Matx33d dh[8];
    for (int k = 0; k < 8; ++k) {
      std::array<Vec2, 4> plus = local, minus = local;
      (k % 2 == 0 ? plus[k / 2].x : plus[k / 2].y) += kStep;
      (k % 2 == 0 ? minus[k / 2].x : minus[k / 2].y) -= kStep;
      dh[k] = (GridToImage(plus, cells_) - GridToImage(minus, cells_)) * (1.0 / (2 * kStep));
    }
    for (int v = 0; v <= cells_; ++v) {
      for (int u = 0; u <= cells_; ++u) {
        const Vec2 p = internal::ApplyHomography(h, u, v);
        vertices_[v * n + u] = p + origin_;
        const double w = h(2, 0) * u + h(2, 1) * v + h(2, 2);
        float* out = &vertex_jac_[static_cast<size_t>(v * n + u) * 16];
        for (int k = 0; k < 8; ++k) {
          const cv::Matx33d& d = dh[k];
          const double dw = d(2, 0) * u + d(2, 1) * v + d(2, 2);
          out[k] = static_cast<float>((d(0, 0) * u + d(0, 1) * v + d(0, 2) - p.x * dw) / w);
          out[8 + k] = static_cast<float>((d(1, 0) * u + d(1, 1) * v + d(1, 2) - p.y * dw) / w);
        }
      }
    }
    // A trial step that throws a vertex far off the plane (or folds the quad, whose grid then runs to
    // infinity or NaN) has no coverage to speak of: Normal gives it an infinite cost, so the step is
    // refused, and its edges are not walked (a walk is as long as its edge).
    const double reach = std::max(roi_.width, roi_.height);
    valid_ = std::all_of(vertices_.begin(), vertices_.end(), [&](const Vec2& p) {
      return p.x >= roi_.x - reach && p.x <= roi_.x + roi_.width + reach && p.y >= roi_.y - reach &&
             p.y <= roi_.y + roi_.height + reach;
    });
    if (!valid_) return;
    const int width = roi_.width, height = roi_.height;
    // Each row's signed-area accumulator has one more column than the plane (what the rightmost
    // column passes on).
    ZeroedBuffer(area_steps_, static_cast<size_t>(height) * (width + 1));
    Buffer(slopes_, static_cast<size_t>(roi_.area()) * kSlopes);  // zeroed per pixel in AddEdges
    ZeroedBuffer(on_boundary_, static_cast<size_t>(roi_.area()));
    boundary_.clear();
    // The boundary pixels' box (BlurSlopes' window) from the runs' vertices, a pixel wider each way
    // for round-off at a pixel's edge, within the plane: a walk visits only pixels between its ends.
    // It may hold pixels no edge crosses, whose slopes BlurSlopes zeroes and adds as zeros (the same
    // sums). Taking the box pixel by pixel in AddEdges was 0.6 % of Detect's instructions (callgrind,
    // 640x480 with 20 markers).
    double low_x = std::numeric_limits<double>::infinity(), low_y = low_x, high_x = -low_x, high_y = -low_x;
    // A run of black cells along a row is one convex quad under the homography: fewer, larger
    // polygons and no shared edges inside a run.
    for (int row = 0; row < cells_; ++row) {
      const uchar* bits = black_.ptr<uchar>(row);
      for (int col = 0; col < cells_;) {
        if (!bits[col]) {
          ++col;
          continue;
        }
        int end = col;
        while (end < cells_ && bits[end]) ++end;
        const int ids[4] = {row * n + col, row * n + end, (row + 1) * n + end, (row + 1) * n + col};
        std::array<Vec2, 4> q;
        for (int i = 0; i < 4; ++i) {
          q[i] = vertices_[ids[i]];
          low_x = std::min(low_x, q[i].x);
          high_x = std::max(high_x, q[i].x);
          low_y = std::min(low_y, q[i].y);
          high_y = std::max(high_y, q[i].y);
        }
        AddEdges(q, ids);
        col = end;
      }
    }
    // Plane column (row) of image x (y): floor(x + 0.5 - roi_.x) (see AddEdges). The vertices lie
    // within `reach` of the plane (valid_): no int overflow.
    const auto plane = [](double v, int origin) { return internal::FloorInt(v + 0.5 - origin); };
    boundary_box_ = {width, height, -1, -1};  // empty
    if (low_x <= high_x) {
      boundary_box_ = {std::max(0, plane(low_x, roi_.x) - 1), std::max(0, plane(low_y, roi_.y) - 1),
                       std::min(width - 1, plane(high_x, roi_.x) + 1), std::min(height - 1, plane(high_y, roi_.y) + 1)};
    }
    SumRows(area_steps_.data(), width, height, Buffer(coverage_, static_cast<size_t>(roi_.area())));
  }

  // The coverage (and, with `jac`, its corner derivatives) at every sample after a Gaussian blur of
  // the given variance. The coverage plane is blurred along rows over the whole coverage area, then
  // along columns on the rows that hold samples; the corner derivatives, non-zero only on the pixels
  // a cell boundary crosses, are scattered along rows from those pixels alone and blurred along
  // columns only at the samples.
  // The start's brightness-and-contrast fit and the first normal equations blur the same coverage with
  // the same kernel: the second time copies the first's result (see Adopt).
  ARUCOTAG_VECTOR_CLONES void Blurred(double variance, std::vector<float>& cover, std::vector<float>* jac) {
    if (!(variance == kernel_variance_)) {
      kernel_ = KernelFor(variance);
      kernel_variance_ = variance;
      blurred_ = false;
    }
    const Kernel& kernel = kernel_;
    const int r = kernel.radius;
    std::array<float, 2 * kBlurRadius + 1> taps;
    for (int k = 0; k < 2 * kBlurRadius + 1; ++k) taps[k] = static_cast<float>(kernel.taps[k]);
    const float* tap = taps.data() + kBlurRadius;  // tap[k], k in [-r, r]
    const int width = roi_.width;
    const size_t n = samples_.size();
    if (!blurred_) {
      Buffer(blurred_cover_, n);
      Buffer(rows_, static_cast<size_t>(roi_.area()));
      Buffer(column_, static_cast<size_t>(width));
      static_assert(kBlurRadius == 5, "one case per kernel radius");
      switch (r) {  // the taps unrolled
        case 1: BlurCoverage<1>(tap, blurred_cover_); break;
        case 2: BlurCoverage<2>(tap, blurred_cover_); break;
        case 3: BlurCoverage<3>(tap, blurred_cover_); break;
        case 4: BlurCoverage<4>(tap, blurred_cover_); break;
        default: BlurCoverage<kBlurRadius>(tap, blurred_cover_); break;
      }
      blurred_ = true;
    }
    std::copy_n(blurred_cover_.data(), n, Buffer(cover, n));
    if (!jac) return;
    Buffer(slope_rows_, static_cast<size_t>(roi_.area()) * kSlopes);
    Buffer(*jac, n * kSlopes);
    switch (r) {  // the taps unrolled, as for the coverage
      case 1: BlurSlopes<1>(tap, jac->data()); break;
      case 2: BlurSlopes<2>(tap, jac->data()); break;
      case 3: BlurSlopes<3>(tap, jac->data()); break;
      case 4: BlurSlopes<4>(tap, jac->data()); break;
      default: BlurSlopes<kBlurRadius>(tap, jac->data()); break;
    }
  }

  // Takes `cover`, what Blurred(variance, cover, nullptr) gave for the corners covered now, as the
  // blurred coverage for that variance: the start tries several variances and keeps the best one's.
  void Adopt(double variance, const std::vector<float>& cover) {
    kernel_ = KernelFor(variance);
    kernel_variance_ = variance;
    std::copy_n(cover.data(), samples_.size(), Buffer(blurred_cover_, samples_.size()));
    blurred_ = true;
  }

 private:
  // Blurred's coverage passes for a kernel of radius R: rows over the samples' columns, then columns
  // one sample row at a time (samples come in row order). Each output sums the same taps in the same
  // order as over the whole plane; the rows and columns no sample reads, and each row's copy padded
  // with zeros, were a sixth of Blurred's instructions.
  template <int R>
  ARUCOTAG_INLINE void BlurCoverage(const float* tap, std::vector<float>& cover) {
    static_assert(R >= 1 && R <= kBlurRadius, "a kernel radius");
    const int width = roi_.width;
    // Rows: the columns that hold samples, on the rows the column pass reads. The plane reaches
    // kBlurRadius past every sample, so no tap falls outside it.
    const int columns = sampled_.x1 - sampled_.x0 + 1;
    for (int y = sampled_.y0 - R; y <= sampled_.y1 + R; ++y) {
      const size_t at = static_cast<size_t>(y) * width + sampled_.x0;
      Convolve<R>(&coverage_[at], 1, tap, &rows_[at], columns);
    }
    float* sum = column_.data();
    for (const SampleRow& row : sample_rows_) {
      const float* in = &rows_[static_cast<size_t>(row.y) * width + row.x0];
      if (row.end - row.first == row.x1 - row.x0) {
        // Every pixel of the row's span is a sample: straight into place.
        Convolve<R>(in, width, tap, &cover[row.first], row.x1 - row.x0);
        continue;
      }
      Convolve<R>(in, width, tap, sum + row.x0, row.x1 - row.x0);
      for (int i = row.first; i < row.end; ++i) cover[i] = sum[samples_[i].x - roi_.x];
    }
  }

  // Blurred's corner derivatives for a kernel of radius R. The scatter reaches the boundary pixels'
  // rows, R columns either side of them: only that window is zeroed (the whole plane was 3-4 % of
  // Detect's instructions), and the column pass reads nothing outside it. Pixels R or more inside
  // the plane's and the window's bounds (nearly all: the plane reaches kBlurRadius past every sample)
  // take every tap with no bound tested per pixel; with the radius a constant the taps unroll.
  // Callgrind of Detect against one loop for every radius with bounds per pixel: the distant set
  // 143.4 -> 138.7 M, the dim one 126.7 -> 122.1 M, the photos 61.3 -> 60.4 M, every corner the
  // same to the bit (each sum adds the same terms in the same order).
  template <int R>
  ARUCOTAG_INLINE void BlurSlopes(const float* tap, float* jac) {
    static_assert(R >= 1 && R <= kBlurRadius, "a kernel radius");
    const int width = roi_.width;
    const int x0 = std::max(0, boundary_box_.x0 - R), x1 = std::min(width - 1, boundary_box_.x1 + R);
    const int y0 = boundary_box_.y0, y1 = boundary_box_.y1;
    for (int y = y0; y <= y1; ++y) {
      std::fill_n(&slope_rows_[(static_cast<size_t>(y) * width + x0) * kSlopes], (x1 - x0 + 1) * kSlopes, 0.0f);
    }
    for (const int at : boundary_) {
      SlopeVector in, out;
      LoadSlopes(&slopes_[static_cast<size_t>(at) * kSlopes], in);
      const int x = at % width;
      float* centre = &slope_rows_[static_cast<size_t>(at) * kSlopes];
      if (x >= R && x + R < width) {
        for (int k = -R; k <= R; ++k) {
          LoadSlopes(centre + k * kSlopes, out);
          StoreSlopes(centre + k * kSlopes, out + tap[k] * in);
        }
        continue;
      }
      for (int k = std::max(-R, -x); k <= std::min(R, width - 1 - x); ++k) {
        LoadSlopes(centre + k * kSlopes, out);
        StoreSlopes(centre + k * kSlopes, out + tap[k] * in);
      }
    }
    const ptrdiff_t stride = static_cast<ptrdiff_t>(width) * kSlopes;
    for (size_t i = 0; i < samples_.size(); ++i) {
      const int x = samples_[i].x - roi_.x, y = samples_[i].y - roi_.y;
      SlopeVector sum = {}, in;
      const float* centre = &slope_rows_[(static_cast<size_t>(y) * width + x) * kSlopes];
      if (x < x0 || x > x1) {
        // Outside the window the plane is zero: no terms (adding zeros changed no sum).
      } else if (y - R >= y0 && y + R <= y1) {
        for (int k = -R; k <= R; ++k) {
          LoadSlopes(centre + k * stride, in);
          sum += tap[k] * in;
        }
      } else {
        for (int k = std::max(-R, y0 - y); k <= std::min(R, y1 - y); ++k) {
          LoadSlopes(centre + k * stride, in);
          sum += tap[k] * in;
        }
      }
      StoreSlopes(&jac[i * kSlopes], sum);
    }
  }

  // Samples: pixels whose centre lies on the marker or within half a cell outside it (the quiet zone
  // every printed marker needs), fully inside the image. Coverage is computed over their bounding box
  // widened by the blur kernel's radius.
  void SelectPixels(const std::array<Vec2, 4>& corners) {
    std::array<Vec2, 4> local;
    for (int i = 0; i < 4; ++i) local[i] = corners[i] - origin_;
    const cv::Matx33d to_image = GridToImage(local, cells_);
    const cv::Matx33d to_grid = to_image.inv();
    constexpr double kMargin = 0.5;
    const double lo = -kMargin, hi = cells_ + kMargin;
    double x0 = 1e9, x1 = -1e9, y0 = 1e9, y1 = -1e9;
    std::array<Vec2, 4> outline;
    int i = 0;
    for (const Vec2& g : {Vec2(lo, lo), Vec2(hi, lo), Vec2(hi, hi), Vec2(lo, hi)}) {
      const Vec2 p = internal::ApplyHomography(to_image, g.x, g.y) + origin_;
      outline[i++] = p;
      x0 = std::min(x0, p.x);
      x1 = std::max(x1, p.x);
      y0 = std::min(y0, p.y);
      y1 = std::max(y1, p.y);
    }
    const cv::Rect box =
        cv::Rect(cv::Point(static_cast<int>(std::floor(x0)), static_cast<int>(std::floor(y0))),
                 cv::Point(static_cast<int>(std::ceil(x1)) + 1, static_cast<int>(std::ceil(y1)) + 1)) &
        cv::Rect(1, 1, grey_.cols - 2, grey_.rows - 2);
    double shoelace = 0.0;
    for (int k = 0; k < 4; ++k) shoelace += Cross(outline[k], outline[(k + 1) % 4]);
    area_ = 0.5 * std::abs(shoelace);
    // Cells of 4 px or more: every other pixel (a checkerboard) still sees each cell edge from both
    // sides many times over, and halves the per-sample work. Markers of more than kMaxSamples such
    // pixels: one pixel in `every`, on the lattice (x + step y) % every == 0 with step near
    // sqrt(every) and prime to it -- samples spread evenly in 2D and in every row and every column, so
    // each cell edge keeps samples among the pixels it crosses (the checkerboard is every = 2, step 1).
    const double cell = std::sqrt(area_) / (cells_ + 2 * kMargin);
    int every = cell >= kCheckerboardCell ? 2 : 1;
    if (area_ / every > kMaxSamples) every = static_cast<int>(std::ceil(area_ / kMaxSamples));
    int step = std::max(1, static_cast<int>(std::lround(std::sqrt(every))));
    while (std::gcd(step, every) != 1) ++step;
    area_ /= every;
    roi_ = cv::Rect(box.x - kBlurRadius, box.y - kBlurRadius, box.width + 2 * kBlurRadius,
                    box.height + 2 * kBlurRadius);
    // Each row is tested only where it crosses the outline (a convex quad) and a pixel either side
    // for round-off, on the lattice's pixels alone: the same samples as testing every pixel of the
    // box, without the homography at the box's corners outside a tilted marker. The samples' rows
    // and bounds, in plane coordinates, for the blur, as they come.
    sample_rows_.clear();
    sampled_ = {roi_.width, roi_.height, -1, -1};
    for (int y = box.y; y < box.y + box.height; ++y) {
      double from, to;
      if (!internal::RowSpan(outline, static_cast<double>(y), from, to)) continue;
      const int first = std::max(box.x, static_cast<int>(std::floor(from)) - 1);
      const int last = std::min(box.x + box.width - 1, static_cast<int>(std::ceil(to)) + 1);
      if (first > last) continue;
      const float* row = grey_.ptr<float>(y);
      const int phase = (first + step * y) % every;
      // A pixel a whole pixel inside the span is inside the outline (a straight-edged quad) by far
      // more than any round-off: only those near its ends (x <= from + 1 or x >= to - 1, for an
      // integer x) take the homography.
      const int near_from = static_cast<int>(std::floor(from + 1.0)), near_to = static_cast<int>(std::ceil(to - 1.0));
      const size_t row_first = samples_.size();
      for (int x = phase == 0 ? first : first + every - phase; x <= last; x += every) {
        if (x <= near_from || x >= near_to) {
          const Vec2 g = internal::ApplyHomography(to_grid, x - origin_.x, y - origin_.y);
          if (g.x < lo || g.x > hi || g.y < lo || g.y > hi) continue;
        }
        samples_.push_back({x, y, static_cast<double>(row[x])});
      }
      if (samples_.size() == row_first) continue;
      const int plane_y = y - roi_.y;
      const int x0 = samples_[row_first].x - roi_.x, x1 = samples_.back().x - roi_.x + 1;
      sample_rows_.push_back({plane_y, static_cast<int>(row_first), static_cast<int>(samples_.size()), x0, x1});
      sampled_ = {std::min(sampled_.x0, x0), std::min(sampled_.y0, plane_y), std::max(sampled_.x1, x1 - 1),
                  std::max(sampled_.y1, plane_y)};
    }
  }

  // The quad's edges, each walked through the pixels it crosses: in each, its signed area goes to the
  // row's steps (AddEdgeArea; Cover sums them into the coverage), and the edge's share of the corner
  // derivatives to the pixel's slopes (the length of edge inside the pixel, split between its two end
  // vertices), the pixel to the boundary list. Only the pixels the edges cross are
  // visited: classifying every pixel of each quad's outline against its four edges and clipping it
  // cost twice as many instructions.
  void AddEdges(const std::array<Vec2, 4>& q, const int ids[4]) {
    const double s = Orientation(q.data(), q.size());
    const int width = roi_.width, height = roi_.height;
    // Pixel (x, y) covers [x - 0.5, x + 0.5] x [y - 0.5, y + 0.5]: plane column x - roi_.x.
    const Vec2 shift(0.5 - roi_.x, 0.5 - roi_.y);
    for (int e = 0; e < 4; ++e) {
      const Vec2 a = q[e] + shift, b = q[(e + 1) % 4] + shift;
      const Vec2 d = b - a;
      // Outward unit normal times edge length: (dy, -dx) for a positively oriented quad.
      const Vec2 nl(s * d.y, -s * d.x);
      SlopeVector ja_x, ja_y, jb_x, jb_y;
      LoadSlopes(&vertex_jac_[ids[e] * 16], ja_x);
      LoadSlopes(&vertex_jac_[ids[e] * 16 + 8], ja_y);
      LoadSlopes(&vertex_jac_[ids[(e + 1) % 4] * 16], jb_x);
      LoadSlopes(&vertex_jac_[ids[(e + 1) % 4] * 16 + 8], jb_y);
      AddEdgeArea(a, b, s, width, height, area_steps_.data(), [&](int ix, int iy, double t0, double t1) {
        const int at = iy * width + ix;
        float* out = &slopes_[static_cast<size_t>(at) * kSlopes];
        if (!on_boundary_[static_cast<size_t>(at)]) {
          on_boundary_[static_cast<size_t>(at)] = 1;
          boundary_.push_back(at);
          std::fill_n(out, kSlopes, 0.0f);
        }
        const double wb = 0.5 * (t1 * t1 - t0 * t0), wa = (t1 - t0) - wb;
        const float ax = static_cast<float>(wa * nl.x), ay = static_cast<float>(wa * nl.y);
        const float bx = static_cast<float>(wb * nl.x), by = static_cast<float>(wb * nl.y);
        SlopeVector sum;
        LoadSlopes(out, sum);
        StoreSlopes(out, sum + (ax * ja_x + ay * ja_y + bx * jb_x + by * jb_y));
      });
    }
  }

  const cv::Mat& grey_;  // CV_32F
  const cv::Mat& black_;
  const int cells_;
  Vec2 origin_;
  double area_ = 0.0;
  bool covered_ = false;
  bool valid_ = false;
  // The last kernel and whether blurred_cover_ holds the coverage blurred by it (Blurred).
  double kernel_variance_ = std::numeric_limits<double>::quiet_NaN();
  Kernel kernel_;
  bool blurred_ = false;
  std::array<Vec2, 4> covered_corners_;
  cv::Rect roi_;  // coverage area, image coordinates (may reach past the image)
  // A row of samples (plane row y, samples [first, end), plane columns [x0, x1)), and the samples'
  // bounds and a box holding the boundary pixels (plane columns x0..x1, rows y0..y1, inclusive;
  // empty: x1 < x0).
  struct SampleRow {
    int y, first, end, x0, x1;
  };
  struct Bounds {
    int x0, y0, x1, y1;
  } sampled_{}, boundary_box_{};
  // Per-thread scratch reused across fits: the coverage planes of a 56 px marker are a few hundred
  // kB, and fresh allocations of that size cost page faults on every fit.
  struct Scratch {
    std::vector<Sample> samples;
    std::vector<Vec2> vertices;
    std::vector<float> vertex_jac;  // per grid vertex: d x / d corners (8), d y / d corners (8)
    std::vector<float> coverage, slopes, rows, slope_rows, column, blurred_cover;
    std::vector<double> area_steps;
    std::vector<uchar> on_boundary;
    std::vector<int> boundary;
    std::vector<SampleRow> sample_rows;
  };
  static Scratch& ThreadScratch() {
    thread_local Scratch scratch;
    return scratch;
  }
  Scratch& scratch_ = ThreadScratch();
  std::vector<Sample>& samples_ = scratch_.samples;
  std::vector<Vec2>& vertices_ = scratch_.vertices;
  std::vector<float>& vertex_jac_ = scratch_.vertex_jac;
  // The coverage plane, and the corner derivatives of the pixels in `boundary_` (the only non-zero
  // ones; `on_boundary_` marks them).
  std::vector<float>&coverage_ = scratch_.coverage, &slopes_ = scratch_.slopes;
  std::vector<double>& area_steps_ = scratch_.area_steps;
  std::vector<uchar>& on_boundary_ = scratch_.on_boundary;
  std::vector<int>& boundary_ = scratch_.boundary;
  std::vector<SampleRow>& sample_rows_ = scratch_.sample_rows;
  std::vector<float>&rows_ = scratch_.rows, &slope_rows_ = scratch_.slope_rows,
                    &column_ = scratch_.column, &blurred_cover_ = scratch_.blurred_cover;
};

// out[j] = the sum of a[k] * b[j * n + k] over k < n, for j < count: each in float with eight
// running sums (a SlopeVector of them, one vector register), so the loop vectorises (a single running
// sum is a dependency chain the compiler may not reorder). Four columns of b share each pass over a:
// a step's normal equations took 104 separate dot products, each loading a again (callgrind of Detect
// on 640x480 frames of 5 markers: 52.7 -> 51.8 M). Each sum adds the same products in the same order
// as a dot product of its own, so the normal equations are the same to the bit.
ARUCOTAG_VECTOR_CLONES void Dots(const float* a, const float* b, size_t n, int count, float* out) {
  constexpr int kBlock = 4;
  for (int first = 0; first < count; first += kBlock) {
    const int block = std::min(kBlock, count - first);
    const float* columns[kBlock];
    // A last block of fewer columns repeats its last one (sums that are not used).
    for (int j = 0; j < kBlock; ++j) columns[j] = b + static_cast<size_t>(first + std::min(j, block - 1)) * n;
    SlopeVector lanes[kBlock] = {};
    size_t k = 0;
    for (; k + 8 <= n; k += 8) {
      SlopeVector x, y;
      LoadSlopes(a + k, x);
      for (int j = 0; j < kBlock; ++j) {
        LoadSlopes(columns[j] + k, y);
        lanes[j] += x * y;
      }
    }
    for (int j = 0; j < block; ++j) {
      float sum = 0.0f;
      for (size_t t = k; t < n; ++t) sum += a[t] * columns[j][t];
      for (int i = 0; i < 8; ++i) sum += lanes[j][i];
      out[first + j] = sum;
    }
  }
}

// Cost evaluations on this thread (internal::PatternFitEvaluations), and the start's blur variances
// tried (internal::PatternFitBlurStarts).
thread_local size_t evaluations = 0;
thread_local size_t blur_starts = 0;

// Cost of the model at `params` and, with jtj/jtr, its Huber-weighted normal equations; with
// `outliers`, the share of pixels the model misses by more than a quarter of its contrast. Per-pixel
// work is in float (sums of a few thousand terms; the step it gives is exact to far below 0.001 px).
// The Jacobian is kept by columns, each pixel's row scaled by the square root of its Huber weight,
// so that J^T W J and J^T W r are dot products of whole columns. Without kEquations the cost (and
// `outliers`) alone: jtj and jtr are not touched. Built once for each, so that neither pays for the
// other's tests in its per-pixel loop.
template <bool kEquations>
double Evaluate(PatternFit& fit, const double* params, double scale, cv::Matx<double, kParams, kParams>* jtj,
                cv::Matx<double, kParams, 1>* jtr, double* outliers) {
  std::array<Vec2, 4> corners;
  for (int i = 0; i < 4; ++i) corners[i] = {params[2 * i], params[2 * i + 1]};
  thread_local std::vector<float> cover, jac, wider, columns;
  fit.Cover(corners);
  if (!fit.valid()) return std::numeric_limits<double>::infinity();
  fit.Blurred(params[kBlur], cover, kEquations ? &jac : nullptr);
  // The blur derivative by a forward difference: the sampled kernel has no simple closed form.
  const double blur_step = 0.02 + 0.02 * params[kBlur];
  if (kEquations) fit.Blurred(params[kBlur] + blur_step, wider, nullptr);
  const auto& samples = fit.samples();
  const size_t n = samples.size();
  // Columns 0..12: the parameters' derivatives; column 13: the residuals.
  constexpr int kResidual = kParams;
  if (kEquations) Buffer(columns, n * (kParams + 1));
  double cost = 0.0;
  int missed = 0;
  const float contrast = static_cast<float>(params[9]), quarter = 0.25f * std::abs(contrast);
  const float blur_scale = static_cast<float>(params[9] / blur_step);
  for (size_t k = 0; k < n; ++k) {
    const double dx = samples[k].x - fit.origin().x, dy = samples[k].y - fit.origin().y;
    const double model = params[8] + params[9] * cover[k] + params[10] * dx + params[11] * dy;
    const double r = samples[k].grey - model;
    // Huber: pixels the pattern cannot explain (a glint, an occluder) count linearly.
    const double a = std::abs(r);
    cost += a <= scale ? 0.5 * r * r : scale * (a - 0.5 * scale);
    missed += a > quarter;
    if (!kEquations) continue;
    const float root = a <= scale ? 1.0f : static_cast<float>(std::sqrt(scale / a));
    float* column = columns.data() + k;
    for (int p = 0; p < 8; ++p) column[p * n] = root * contrast * jac[k * 8 + p];
    column[8 * n] = root;
    column[9 * n] = root * cover[k];
    column[10 * n] = root * static_cast<float>(dx);
    column[11 * n] = root * static_cast<float>(dy);
    column[kBlur * n] = root * blur_scale * (wider[k] - cover[k]);
    column[kResidual * n] = root * static_cast<float>(r);
  }
  if (outliers) *outliers = static_cast<double>(missed) / static_cast<double>(n);
  if (kEquations) {
    // Column p against columns p..12 and the residuals (which follow them).
    float dots[kParams + 1];
    for (int p = 0; p < kParams; ++p) {
      Dots(columns.data() + p * n, columns.data() + p * n, n, kResidual + 1 - p, dots);
      for (int q = p; q < kParams; ++q) (*jtj)(p, q) = (*jtj)(q, p) = dots[q - p];
      (*jtr)(p) = dots[kResidual - p];
    }
  }
  return cost;
}

// Evaluate with the normal equations, and without: each counted in `evaluations`.
double Normal(PatternFit& fit, const double* params, double scale, cv::Matx<double, kParams, kParams>* jtj,
              cv::Matx<double, kParams, 1>* jtr, double* outliers) {
  ++evaluations;
  return Evaluate<true>(fit, params, scale, jtj, jtr, outliers);
}
double Cost(PatternFit& fit, const double* params, double scale, double* outliers) {
  ++evaluations;
  return Evaluate<false>(fit, params, scale, nullptr, nullptr, outliers);
}

// x solving a x = b for a symmetric positive definite `a`; false when it is not. The Cholesky solver
// cv::solve(DECOMP_CHOLESKY) runs, called directly: the same arithmetic, so the same step, without
// cv::solve's conversions to cv::Mat, buffer and copies (a third of the 9.5 k instructions a solve of
// 13 unknowns took that way; callgrind of Detect on bench's tag36h11 set 138.7 -> 138.4 M).
bool SolveCholesky(cv::Matx<double, kParams, kParams> a, const cv::Matx<double, kParams, 1>& b,
                   cv::Matx<double, kParams, 1>& x) {
  x = b;
  return cv::hal::Cholesky64f(a.val, kParams * sizeof(double), kParams, x.val, sizeof(double), 1);
}

// The fit itself, on a CV_32F image: refines `corners` in place (its pixel coordinates); false when
// the result is not to be trusted.
// `blur` in: the blur variance to start from (a tracked marker's from the last frame), or < 0 to
// try kStartBlurVariances; out: the fitted one.
bool FitPattern(const cv::Mat& grey, const cv::Mat& black, std::array<Vec2, 4>& corners, double& blur,
                double last_step) {
  const int cells = black.rows;
  const std::array<Vec2, 4> start = corners;
  PatternFit fit(grey, black, cells, start);
  // Cut by the image border (the pattern would be fitted to part of itself), or too few pixels to
  // say anything.
  if (static_cast<double>(fit.size()) < 0.9 * fit.area() || fit.size() < 2 * static_cast<size_t>(cells * cells)) {
    return false;
  }

  double params[kParams] = {};
  for (int i = 0; i < 4; ++i) {
    params[2 * i] = start[i].x;
    params[2 * i + 1] = start[i].y;
  }
  // Brightness, contrast and blur at the start: for each of a few blur widths a linear least-squares
  // fit of brightness and contrast with the corners held; the best of them starts the fit (starting
  // from one fixed width cost one or two extra iterations on sharp or very blurred markers). A
  // tracked marker starts from the width its last frame's fit found.
  {
    thread_local std::vector<float> cover, best_cover;
    fit.Cover(start);
    if (!fit.valid()) return false;
    double best = std::numeric_limits<double>::infinity();
    double last = -1.0;  // the variance the fit's coverage is blurred with now
    // The residual of the brightness-and-contrast fit at one variance, which starts the fit when it is
    // the best so far (or, with `first_in_scan`, as good: a variance a scan in order would try first).
    // `keep`: its coverage is copied, for a variance that may not be the last one tried.
    // The normal equations' sums that do not depend on the variance, made once: the pixel count, the
    // grey levels' sum and their sum of squares (each sum in the order a variance's own loop added it,
    // so the same values).
    double count = 0.0, grey_sum = 0.0, yy = 0.0;
    for (size_t k = 0; k < fit.size(); ++k) {
      const double grey_level = fit.samples()[k].grey;
      count += 1.0;
      grey_sum += grey_level;
      yy += grey_level * grey_level;
    }
    const auto try_variance = [&](double variance, bool keep, bool first_in_scan) {
      ++blur_starts;
      fit.Blurred(variance, cover, nullptr);
      last = variance;
      double cover_sum = 0.0, cover_squares = 0.0, cross = 0.0;
      for (size_t k = 0; k < fit.size(); ++k) {
        const double c = cover[k];
        cover_sum += c;
        cover_squares += c * c;
        cross += c * fit.samples()[k].grey;
      }
      const cv::Matx22d a(count, cover_sum, cover_sum, cover_squares);
      const cv::Vec2d b(grey_sum, cross);
      if (std::abs(cv::determinant(a)) < 1e-9) return std::numeric_limits<double>::infinity();
      const cv::Vec2d x = a.inv() * b;
      const double residual = yy - x.dot(b);  // sum of squares left by the least-squares fit
      if (residual < best || (first_in_scan && residual == best)) {
        best = residual;
        params[8] = x[0];
        params[9] = x[1];
        params[kBlur] = variance;
        if (keep) best_cover.assign(cover.begin(), cover.begin() + fit.size());
      }
      return residual;
    };
    if (blur >= 0.0) {
      try_variance(std::min(blur, kMaxBlurVariance), false, false);
    } else {
      // The residual falls towards the marker's blur and rises past it: the middle two variances (0.25
      // and 0.64) tell on which side of them it lies, and only that side is tried on, outwards from
      // them while the residual keeps falling. Three or four blurs instead of five: trying all four of
      // the variances before 0.09 came in order gave the same starts on every bench set (Detect's
      // markers byte-identical), and callgrind of Detect on 640x480/5 51.2 -> 50.1 M, photos 72.4 -> 71.4 M.
      static_assert(std::size(kStartBlurVariances) == 5, "two middle variances, a sharper one and two ends");
      const double sharper = try_variance(kStartBlurVariances[2], true, false);
      const double blurrier = try_variance(kStartBlurVariances[3], true, false);
      if (sharper <= blurrier) {
        const double slight = try_variance(kStartBlurVariances[1], true, true);
        if (slight <= sharper) try_variance(kStartBlurVariances[0], false, true);
      } else {
        try_variance(kStartBlurVariances[4], false, false);
      }
    }
    if (!std::isfinite(best)) return false;
    // The first normal equations blur with the best variance: the last one tried is still there, any
    // other is taken back rather than blurred again.
    if (params[kBlur] != last) fit.Adopt(params[kBlur], best_cover);
  }
  const double contrast = std::abs(params[9]);
  if (!(contrast > 10.0)) return false;  // no pattern to fit (or a wrong id)
  const double scale = 0.1 * contrast;    // Huber threshold: a tenth of the black-white step

  double lambda = 1e-3;
  cv::Matx<double, kParams, kParams> jtj, trial_jtj;
  cv::Matx<double, kParams, 1> jtr, trial_jtr;
  double outliers = 0.0, trial_outliers = 0.0;
  double cost = Normal(fit, params, scale, &jtj, &jtr, &outliers);
  for (int iteration = 0; iteration < kMaxIterations; ++iteration) {
    cv::Matx<double, kParams, kParams> damped = jtj;
    for (int p = 0; p < kParams; ++p) damped(p, p) += lambda * std::max(jtj(p, p), 1e-9);
    cv::Matx<double, kParams, 1> step;
    if (!SolveCholesky(damped, jtr, step)) return false;
    const double blur = params[kBlur] + step(kBlur);
    if (blur < 0.0 || blur > kMaxBlurVariance) {
      // The blur wants past its bound (JPEG and demosaicing sharpen edges beyond a pixel's box):
      // hold it at the bound and solve for the rest, so the step stays a Gauss-Newton step.
      const cv::Matx<double, kParams, 1> held = step;
      for (int p = 0; p < kParams; ++p) damped(kBlur, p) = damped(p, kBlur) = 0.0;
      damped(kBlur, kBlur) = 1.0;
      cv::Matx<double, kParams, 1> rhs = jtr;
      rhs(kBlur) = std::clamp(blur, 0.0, kMaxBlurVariance) - params[kBlur];
      for (int p = 0; p < kParams; ++p) {
        if (p != kBlur) rhs(p) -= jtj(p, kBlur) * rhs(kBlur);
      }
      if (!SolveCholesky(damped, rhs, step)) step = held;
    }
    double largest = 0.0;
    for (int p = 0; p < 8; ++p) largest = std::max(largest, std::abs(step(p)));
    // Converged: the corners would move by less than kConverged. (Testing this before the trial
    // also ends the fit where a tiny step no longer lowers the cost in float arithmetic.)
    if (largest < kConverged) break;
    if (largest < last_step) {
      // This close to the fit the cost is quadratic: the Gauss-Newton step lands on the minimum
      // without an evaluation to confirm it.
      for (int p = 0; p < kParams; ++p) params[p] += step(p);
      params[kBlur] = std::clamp(params[kBlur], 0.0, kMaxBlurVariance);
      break;
    }
    double trial[kParams];
    for (int p = 0; p < kParams; ++p) trial[p] = params[p] + step(p);
    trial[kBlur] = std::clamp(trial[kBlur], 0.0, kMaxBlurVariance);
    const double allowed = iteration >= 3 ? kMaxOutliers : 1.5 * kMaxOutliers;
    // Steps are mostly accepted: the trial's normal equations are the next iteration's. From a start
    // that misses kDoubtfulOutliers of the pixels or more the trial is costed first, and its normal
    // equations only made when the step is taken and the fit not refused (the same decisions).
    double trial_cost = 0.0;
    if (outliers >= kDoubtfulOutliers) {
      trial_cost = Cost(fit, trial, scale, &trial_outliers);
      if (trial_cost < cost) {
        if (trial_outliers > allowed) return false;
        // The same point again (its coverage kept): one evaluation.
        trial_cost = Evaluate<true>(fit, trial, scale, &trial_jtj, &trial_jtr, &trial_outliers);
      }
    } else {
      trial_cost = Normal(fit, trial, scale, &trial_jtj, &trial_jtr, &trial_outliers);
    }
    if (trial_cost < cost) {
      std::copy(trial, trial + kParams, params);
      cost = trial_cost;
      outliers = trial_outliers;
      jtj = trial_jtj;
      jtr = trial_jtr;
      lambda = std::max(lambda * 0.1, 1e-7);
      // A right pattern explains all but a few pixels from its first step on, however far off its
      // start (test_core's accepted fits: at most 4.5 % outliers after the first step, most under
      // 0.3 %; make bench's 3592: at most 6.0 %, from starts that missed up to 39 %); one that still
      // misses more will be refused anyway, so stop paying for it: past 1.5 times the limit from the
      // first step, past the limit itself from the fourth. (Near-markers that hover at 6-7 % otherwise
      // ran all kMaxIterations: 2 ms a fit, 5.9-17 ms on a 64x48 fuzz frame of nine of them. The
      // bleeding prints of the ChArUco photos miss 8-17 % after the first step: refused there rather
      // than two steps later, Detect on the three OpenCV tutorial photos takes 109.5 M instructions
      // instead of 121.3 M, with the same corners.)
      if (outliers > allowed) return false;
    } else {
      // A rejected step this small is at the noise floor: more damping only costs evaluations.
      if (largest < kNoiseFloorStep) break;
      lambda *= 10.0;
      if (lambda > 1e6) break;
    }
  }
  // A fit that wandered off (further than the start can be wrong by) or leaves many pixels unexplained
  // is not trusted.
  if (!(outliers < kMaxOutliers) || std::abs(params[9]) < 0.5 * contrast) return false;
  for (int i = 0; i < 4; ++i) corners[i] = {params[2 * i], params[2 * i + 1]};
  blur = params[kBlur];
  return true;
}

}  // namespace

namespace internal {

cv::Mat PolygonCoverage(const std::vector<cv::Point2d>& polygon, const cv::Size& size) {
  std::vector<double> steps(static_cast<size_t>(size.height) * (size.width + 1), 0.0);
  const double s = Orientation(polygon.data(), polygon.size());
  const Vec2 shift(0.5, 0.5);  // pixel (x, y) covers [x - 0.5, x + 0.5] x [y - 0.5, y + 0.5]
  for (size_t e = 0; e < polygon.size(); ++e) {
    AddEdgeArea(polygon[e] + shift, polygon[(e + 1) % polygon.size()] + shift, s, size.width, size.height,
                steps.data(), [](int, int, double, double) {});
  }
  cv::Mat coverage(size, CV_64F);
  SumRows(steps.data(), size.width, size.height, coverage.ptr<double>());
  return coverage;
}

size_t PatternFitEvaluations() { return evaluations; }
size_t PatternFitBlurStarts() { return blur_starts; }

size_t PatternFitSampleCount(const cv::Mat& grey, int cells, const std::array<cv::Point2f, 4>& corners) {
  cv::Mat patch;
  grey.convertTo(patch, CV_32F);
  const cv::Mat black(cells, cells, CV_8UC1, cv::Scalar(0));
  std::array<Vec2, 4> start;
  for (int i = 0; i < 4; ++i) start[i] = Vec2(corners[i]);
  return PatternFit(patch, black, cells, start).size();
}

}  // namespace internal

bool RefineCornersOnPattern(const cv::Mat& grey, const cv::Mat& black, std::array<cv::Point2f, 4>& corners) {
  float blur = -1.0f;
  return internal::RefineCornersOnPatternFrom(grey, black, corners, blur, internal::kColdLastStep);
}

namespace internal {

bool RefineCornersOnPatternFrom(const cv::Mat& grey, const cv::Mat& black, std::array<cv::Point2f, 4>& corners,
                                float& blur_variance, double last_step) {
  CV_Assert(grey.type() == CV_8UC1 && black.type() == CV_8UC1 && black.rows == black.cols);
  const int cells = black.rows;
  const double side = internal::MeanSide(corners);
  double x0 = 1e9, y0 = 1e9, x1 = -1e9, y1 = -1e9;
  for (int i = 0; i < 4; ++i) {
    x0 = std::min<double>(x0, corners[i].x);
    x1 = std::max<double>(x1, corners[i].x);
    y0 = std::min<double>(y0, corners[i].y);
    y1 = std::max<double>(y1, corners[i].y);
  }
  if (!(side > 0.0) || !std::isfinite(x0 + x1 + y0 + y1)) return false;
  // Off the image: nothing to fit (and no float-to-int overflow below for far-away corners).
  if (x1 < 0.0 || y1 < 0.0 || x0 > grey.cols - 1.0 || y0 > grey.rows - 1.0 || side > kMaxSide) {
    return false;
  }
  // A marker's image is a convex quad; anything else (folded, collapsed) has no homography to fit.
  int turns = 0;
  for (int i = 0; i < 4; ++i) {
    const cv::Point2f a = corners[(i + 1) % 4] - corners[i], b = corners[(i + 2) % 4] - corners[(i + 1) % 4];
    const double cross = static_cast<double>(a.x) * b.y - static_cast<double>(a.y) * b.x;
    if (std::abs(cross) < 1e-3 * side * side) return false;
    turns += cross > 0 ? 1 : -1;
  }
  if (std::abs(turns) != 4) return false;
  // The marker, its quiet-zone strip and room for the blur kernel, as float. (A fit on a 2x2-averaged
  // copy was tried for speed: 4x cheaper, but 0.06 px off on blurred markers, so not used.)
  const double margin = side / cells + kBlurRadius + 2;
  cv::Rect box(cv::Point(static_cast<int>(std::floor(x0 - margin)), static_cast<int>(std::floor(y0 - margin))),
               cv::Point(static_cast<int>(std::ceil(x1 + margin)) + 1, static_cast<int>(std::ceil(y1 + margin)) + 1));
  box &= cv::Rect(0, 0, grey.cols, grey.rows);
  if (box.width < 4 || box.height < 4) return false;
  cv::Mat patch;
  grey(box).convertTo(patch, CV_32F);
  std::array<Vec2, 4> local;
  for (int i = 0; i < 4; ++i) local[i] = {corners[i].x - box.x, corners[i].y - box.y};
  double blur = blur_variance;
  if (!FitPattern(patch, black, local, blur, last_step)) return false;
  std::array<cv::Point2f, 4> refined;
  for (int i = 0; i < 4; ++i) {
    const Vec2 p(local[i].x + box.x, local[i].y + box.y);
    if (cv::norm(p - Vec2(corners[i])) > kMaxMove) return false;
    refined[i] = cv::Point2f(static_cast<float>(p.x), static_cast<float>(p.y));
  }
  corners = refined;
  blur_variance = static_cast<float>(blur);
  return true;
}

}  // namespace internal

}  // namespace arucotag

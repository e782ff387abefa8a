// Quad geometry shared by the core's detection and refinement steps (internal to arucotag_core).
#pragma once

#include <algorithm>
#include <array>
#include <cmath>
#include <limits>
#include <vector>

#include <opencv2/core.hpp>
#include <opencv2/imgproc.hpp>

// The core's per-pixel loops (blur, threshold, normal equations) are arithmetic the compiler
// vectorises: on x86-64 GCC also builds them for AVX2 (8 floats or 16 shorts a step, not SSE2's 4
// or 8) and picks that version when the library loads on any CPU that has AVX2. The clone is chosen
// by the instruction set, not the CPU model: "arch=haswell" is picked on Intel Haswell and later
// alone (an AMD EPYC, and this benchmark machine, ran the SSE2 build; valgrind reports a Haswell, so
// callgrind measured the AVX2 one). Without FMA the AVX2 build rounds every float and double
// operation as the SSE2 build does, so both give the same results.
#if defined(__GNUC__) && !defined(__clang__) && defined(__x86_64__)
#define ARUCOTAG_VECTOR_CLONES __attribute__((target_clones("avx2", "default")))
#else
#define ARUCOTAG_VECTOR_CLONES
#endif
// Products and sums stay separate roundings in a function marked so, even in a build that enables
// FMA (the clones above do not, -march=native does): GCC is told not to fuse them (it would across
// statements), and each product is its own statement for compilers that fuse within one. Its
// results are then the same as a scalar loop's in every build.
#if defined(__GNUC__) && !defined(__clang__)
#define ARUCOTAG_NO_FUSED_MULTIPLY_ADD __attribute__((optimize("fp-contract=off")))
#else
#define ARUCOTAG_NO_FUSED_MULTIPLY_ADD
#endif
// A few byte loops GCC's clones do not vectorise as well are also written by hand for AVX2 on x86-64
// (GCC and Clang build a function marked ARUCOTAG_AVX2 whatever the target's flags are); each is
// called only where CpuHasAvx2(), the portable loop elsewhere.
#if defined(__x86_64__) && (defined(__GNUC__) || defined(__clang__))
#define ARUCOTAG_HAND_AVX2 1
#define ARUCOTAG_AVX2 __attribute__((target("avx2")))
#endif
// Helpers of those loops are inlined into them, so that each clone has its own build of them.
#if defined(__GNUC__)
#define ARUCOTAG_INLINE __attribute__((always_inline)) inline
#else
#define ARUCOTAG_INLINE inline
#endif

namespace arucotag::internal {

#if defined(ARUCOTAG_HAND_AVX2)
/// Whether this CPU runs the ARUCOTAG_AVX2 builds (asked once).
inline bool CpuHasAvx2() {
  static const bool has = __builtin_cpu_supports("avx2");
  return has;
}
#endif

// Four doubles or ints as one value (GCC's and Clang's vector extension): one AVX register, or two
// SSE2 ones.
typedef double Double4 __attribute__((vector_size(4 * sizeof(double))));
typedef int Int4 __attribute__((vector_size(4 * sizeof(int))));

/// Homography of the unit square onto a quad: (0,0)->q0, (1,0)->q1, (1,1)->q2, (0,1)->q3, in closed
/// form (Heckbert), as the 3x3 matrix [a b c; d e f; g h 1] applied to (u, v, 1). A quad whose
/// sides are parallel (or degenerate) gets the affine map.
template <typename Point>
cv::Matx33d SquareToQuad(const std::array<Point, 4>& q) {
  const double x0 = q[0].x, y0 = q[0].y, x1 = q[1].x, y1 = q[1].y, x2 = q[2].x, y2 = q[2].y, x3 = q[3].x,
               y3 = q[3].y;
  const double dx1 = x1 - x2, dx2 = x3 - x2, dx3 = x0 - x1 + x2 - x3;
  const double dy1 = y1 - y2, dy2 = y3 - y2, dy3 = y0 - y1 + y2 - y3;
  double g = 0.0, h = 0.0;
  const double det = dx1 * dy2 - dx2 * dy1;
  if ((dx3 != 0.0 || dy3 != 0.0) && det != 0.0) {
    g = (dx3 * dy2 - dx2 * dy3) / det;
    h = (dx1 * dy3 - dx3 * dy1) / det;
  }
  return {x1 - x0 + g * x1, x3 - x0 + h * x3, x0, y1 - y0 + g * y1, y3 - y0 + h * y3, y0, g, h, 1.0};
}

/// The image of (u, v) under the homography h.
inline cv::Point2d ApplyHomography(const cv::Matx33d& h, double u, double v) {
  const double w = h(2, 0) * u + h(2, 1) * v + h(2, 2);
  return {(h(0, 0) * u + h(0, 1) * v + h(0, 2)) / w, (h(1, 0) * u + h(1, 1) * v + h(1, 2)) / w};
}

/// Where the pixel row at height y crosses the convex quad: from lo to hi (its edges' crossings; a
/// horizontal edge's ends are its neighbours' ends). False when the row misses the quad.
template <typename T>
bool RowSpan(const std::array<cv::Point_<T>, 4>& quad, T y, T& lo, T& hi) {
  lo = std::numeric_limits<T>::infinity();
  hi = -lo;
  for (int e = 0; e < 4; ++e) {
    const cv::Point_<T>&a = quad[e], &b = quad[(e + 1) % 4];
    if ((a.y - y) * (b.y - y) > 0 || a.y == b.y) continue;
    const T x = a.x + (b.x - a.x) * (y - a.y) / (b.y - a.y);
    lo = std::min(lo, x);
    hi = std::max(hi, x);
  }
  return lo <= hi;
}

/// Mean side length (px) of a quad.
inline float MeanSide(const std::array<cv::Point2f, 4>& quad) {
  float s = 0.0f;
  for (int i = 0; i < 4; ++i) s += static_cast<float>(cv::norm(quad[i] - quad[(i + 1) % 4]));
  return 0.25f * s;
}

/// Centre of a quad: the mean of its corners.
inline cv::Point2f Centre(const std::array<cv::Point2f, 4>& c) { return (c[0] + c[1] + c[2] + c[3]) * 0.25f; }

/// Integer bounding box of a quad's corners.
inline cv::Rect Bounds(const std::array<cv::Point2f, 4>& c) {
  return cv::boundingRect(std::vector<cv::Point2f>(c.begin(), c.end()));
}

/// `r` grown by `pad` px on every side, clipped to a frame of size `frame`.
inline cv::Rect Grow(const cv::Rect& r, int pad, const cv::Size& frame) {
  return cv::Rect(r.x - pad, r.y - pad, r.width + 2 * pad, r.height + 2 * pad) & cv::Rect(cv::Point(0, 0), frame);
}

/// Whether two quads' corners, matched in some cyclic order, are closer than `limit` (px, RMS over
/// the four corners): cv::aruco's test for one candidate traced twice (_filterTooCloseCandidates).
inline bool CornersWithin(const std::array<cv::Point2f, 4>& a, const std::array<cv::Point2f, 4>& b, double limit) {
  for (int shift = 0; shift < 4; ++shift) {
    double sum = 0.0;
    for (int c = 0; c < 4; ++c) {
      const cv::Point2f d = a[(c + shift) % 4] - b[c];
      sum += double(d.x) * d.x + double(d.y) * d.y;
    }
    if (sum / 4.0 < limit * limit) return true;
  }
  return false;
}

/// floor(v) as an int, for finite |v| < 2^31: without SSE4.1 (the x86-64 baseline) std::floor is a
/// dozen instructions, and the per-sample loops that read pixels spend more on it than on the reads.
inline int FloorInt(double v) {
  const int truncated = static_cast<int>(v);
  return truncated - (v < truncated);
}

/// Bilinear grey value of an 8-bit image at (x, y) from the pixel (ix, iy) below and left of it,
/// which has a right and a lower neighbour.
inline double Interpolate(const cv::Mat& grey, int ix, int iy, double x, double y) {
  const double a = x - ix, b = y - iy;
  const uchar* r0 = grey.ptr<uchar>(iy) + ix;
  const uchar* r1 = r0 + grey.step[0];
  const double top = r0[0] + a * (r0[1] - r0[0]), bottom = r1[0] + a * (r1[1] - r1[0]);
  return top + b * (bottom - top);
}

/// Bilinear grey value of an 8-bit single-channel image, at least 2x2, at (x, y); the caller keeps
/// (x, y) within [0, cols - 1] x [0, rows - 1].
inline double SampleBilinear(const cv::Mat& grey, double x, double y) {
  return Interpolate(grey, std::min(FloorInt(x), grey.cols - 2), std::min(FloorInt(y), grey.rows - 2), x, y);
}

/// SampleBilinear where (x, y) is known to lie in [0, cols - 2] x [0, rows - 2]: truncation is the
/// floor there and no clamp is needed (a fifth fewer instructions in the edge fit, whose profiles
/// are checked to lie inside). The same arithmetic, so the same values.
inline double SampleInside(const cv::Mat& grey, double x, double y) {
  return Interpolate(grey, static_cast<int>(x), static_cast<int>(y), x, y);
}

}  // namespace arucotag::internal

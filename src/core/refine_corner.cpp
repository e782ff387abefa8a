// Corner refinement of the fast path: cv::cornerSubPix, corner by corner. It gives kSubpix its
// corners, and the edge fit its start for markers that no cv::aruco window finds (identify.cpp).
#include "refine_corner.hpp"

#include "geometry.hpp"

#include <algorithm>
#include <cfloat>
#include <cmath>
#include <vector>

#include <opencv2/core/hal/intrin.hpp>

namespace arucotag::internal {

// cv::cornerSubPix (zero zone off) for one point, same iteration, stopping rule and fallback, in
// float and 4-wide SIMD: OpenCV's version, in double with a getRectSubPix call per iteration, is
// the main cost of a frame with many markers. Converges to the same point within a few
// thousandths of a pixel.
cv::Point2f RefineCorner(const cv::Mat& grey, cv::Point2f start, int half, int max_iterations, double epsilon,
                         float reach) {
  const int win = 2 * half + 1;
  const int wpad = (win + 3) & ~3;  // columns processed, 4 at a time; the mask is 0 past win
  const int stride = wpad + 4;      // patch columns: one more each side for the gradient, rounded to 4
  const int patch_rows = win + 2;
  thread_local std::vector<float> mask, buffer;
  thread_local int mask_half = -1;
  if (mask_half != half) {
    mask.assign(static_cast<size_t>(win) * wpad, 0.0f);
    for (int i = 0; i < win; ++i) {
      const float y = float(i - half) / half;
      const float vy = std::exp(-y * y);
      for (int j = 0; j < win; ++j) {
        const float x = float(j - half) / half;
        mask[static_cast<size_t>(i) * wpad + j] = vy * std::exp(-x * x);
      }
    }
    mask_half = half;
  }
  buffer.resize(static_cast<size_t>(patch_rows) * stride + 4);
  const int iterations = std::min(std::max(max_iterations, 1), 100);
  const double eps_sq = epsilon * epsilon;
  cv::Point2f c = start;
  for (int iter = 0; iter < iterations; ++iter) {
    // getRectSubPix: bilinear samples of the (win + 2)^2 patch centred on c, edges replicated.
    const float cx = c.x - (win + 1) * 0.5f, cy = c.y - (win + 1) * 0.5f;
    const int ix = cvFloor(cx), iy = cvFloor(cy);
    const float a = cx - ix, bf = cy - iy;
    const float a11 = (1.f - a) * (1.f - bf), a12 = a * (1.f - bf), a21 = (1.f - a) * bf, a22 = a * bf;
    // The SIMD loads read 8 bytes from each of the last columns: stay that far inside the frame.
    const bool inside = ix >= 0 && iy >= 0 && ix + stride + 4 < grey.cols && iy + patch_rows < grey.rows;
    for (int i = 0; i < patch_rows; ++i) {
      float* out = &buffer[static_cast<size_t>(i) * stride];
      if (inside) {
        const uchar* r0 = grey.ptr<uchar>(iy + i) + ix;
        const uchar* r1 = grey.ptr<uchar>(iy + i + 1) + ix;
#if CV_SIMD128
        const cv::v_float32x4 w11 = cv::v_setall_f32(a11), w12 = cv::v_setall_f32(a12), w21 = cv::v_setall_f32(a21),
                              w22 = cv::v_setall_f32(a22);
        // 4 pixels from any byte address. Not v_load_expand_q: it reads them as one int
        // (*(const int*)p), undefined at an odd address and reported by UBSan. v_load_expand's
        // 8-byte load takes any address and costs the same; the upper 4 are dropped.
        const auto load = [](const uchar* p) {
          cv::v_uint32x4 low, high;
          cv::v_expand(cv::v_load_expand(p), low, high);
          return cv::v_cvt_f32(cv::v_reinterpret_as_s32(low));
        };
        for (int j = 0; j < stride; j += 4) {
          cv::v_store(out + j, load(r0 + j) * w11 + load(r0 + j + 1) * w12 + load(r1 + j) * w21 + load(r1 + j + 1) * w22);
        }
#else
        for (int j = 0; j < stride; ++j) out[j] = r0[j] * a11 + r0[j + 1] * a12 + r1[j] * a21 + r1[j + 1] * a22;
#endif
      } else {
        const auto at = [&](int y, int x) {
          return float(grey.ptr<uchar>(std::min(std::max(y, 0), grey.rows - 1))[std::min(std::max(x, 0), grey.cols - 1)]);
        };
        for (int j = 0; j < stride; ++j) {
          const int x = ix + j, y = iy + i;
          out[j] = at(y, x) * a11 + at(y, x + 1) * a12 + at(y + 1, x) * a21 + at(y + 1, x + 1) * a22;
        }
      }
    }
    double sa = 0, sb = 0, sc = 0, bb1 = 0, bb2 = 0;
#if CV_SIMD128
    const cv::v_float32x4 offsets(0.f, 1.f, 2.f, 3.f);
    cv::v_float32x4 va = cv::v_setzero_f32(), vb = va, vc = va, v1 = va, v2 = va;
    for (int i = 0; i < win; ++i) {
      const float* row = &buffer[static_cast<size_t>(i + 1) * stride + 1];
      const float* m = &mask[static_cast<size_t>(i) * wpad];
      const cv::v_float32x4 py = cv::v_setall_f32(float(i - half));
      for (int j = 0; j < wpad; j += 4) {
        const cv::v_float32x4 gx = cv::v_load(row + j + 1) - cv::v_load(row + j - 1);
        const cv::v_float32x4 gy = cv::v_load(row + j + stride) - cv::v_load(row + j - stride);
        const cv::v_float32x4 w = cv::v_load(m + j);
        const cv::v_float32x4 gxx = gx * gx * w, gxy = gx * gy * w, gyy = gy * gy * w;
        const cv::v_float32x4 px = cv::v_setall_f32(float(j - half)) + offsets;
        va += gxx;
        vb += gxy;
        vc += gyy;
        v1 += gxx * px + gxy * py;
        v2 += gxy * px + gyy * py;
      }
    }
    sa = cv::v_reduce_sum(va);
    sb = cv::v_reduce_sum(vb);
    sc = cv::v_reduce_sum(vc);
    bb1 = cv::v_reduce_sum(v1);
    bb2 = cv::v_reduce_sum(v2);
#else
    for (int i = 0; i < win; ++i) {
      const float* row = &buffer[static_cast<size_t>(i + 1) * stride + 1];
      const float* m = &mask[static_cast<size_t>(i) * wpad];
      const float py = float(i - half);
      for (int j = 0; j < win; ++j) {
        const float gx = row[j + 1] - row[j - 1], gy = row[j + stride] - row[j - stride];
        const float gxx = gx * gx * m[j], gxy = gx * gy * m[j], gyy = gy * gy * m[j];
        const float px = float(j - half);
        sa += gxx;
        sb += gxy;
        sc += gyy;
        bb1 += gxx * px + gxy * py;
        bb2 += gxy * px + gyy * py;
      }
    }
#endif
    const double det = sa * sc - sb * sb;
    if (std::fabs(det) <= DBL_EPSILON * DBL_EPSILON) break;
    const double scale = 1.0 / det;
    const cv::Point2f next(static_cast<float>(c.x + sc * scale * bb1 - sb * scale * bb2),
                           static_cast<float>(c.y - sb * scale * bb1 + sa * scale * bb2));
    const double step = double(next.x - c.x) * (next.x - c.x) + double(next.y - c.y) * (next.y - c.y);
    c = next;
    if (c.x < 0 || c.x >= grey.cols || c.y < 0 || c.y >= grey.rows) break;
    if (step <= eps_sq) break;
  }
  // Too far from the start (`reach`, or the half window): poor convergence, keep the start (OpenCV's
  // rule).
  const float limit = reach > 0.0f ? reach : static_cast<float>(half);
  if (std::fabs(c.x - start.x) > limit || std::fabs(c.y - start.y) > limit) c = start;
  return c;
}

namespace {
// Share of a cell the half window may span: the border cell reaches one cell in from the corner,
// and the blur a little further. Measured on the rendered bench sets (make bench, ours_subpix).
constexpr double kCornerWindowCells = 0.75;
// The smallest half window (unless configured smaller): on cells under 2.7 px three quarters of a
// cell is 1 px, a 3 x 3 window whose central differences barely see the corner's two edges. The
// corner still moves at most the cell-fitted half window from its start (the window's own reach put
// the p95 of 14-17 px DICT_4X4_50 markers at no refinement's, test_synthetic
// SubpixImprovesOnNoRefinementForSmallMarkers). bench_detect, tag36h11 of 13-30 px (2-3 px cells, the
// distant set): corner error median 0.418 -> 0.359 px, p95 0.851 -> 0.734; on the markers cv::aruco's
// subpix also finds, 0.328 / 0.716 -> 0.307 / 0.518 against its 0.322 / 1.847.
constexpr int kMinCornerHalfWindow = 2;

// kCornerWindowCells of a cell, within 1 and `configured`.
int CellHalfWindow(float side, int cells, int configured) {
  const double cell = static_cast<double>(side) / std::max(cells, 1);
  const int fitting = std::isfinite(cell) ? static_cast<int>(std::min(1e6, std::floor(kCornerWindowCells * cell))) : 1;
  return std::max(1, std::min(configured, fitting));
}
}  // namespace

int MarkerCornerHalfWindow(float side, int cells, int configured) {
  return std::max(CellHalfWindow(side, cells, configured), std::min(configured, kMinCornerHalfWindow));
}

void RefineMarkerCorners(const cv::Mat& grey, std::array<cv::Point2f, 4>& corners, int cells, int configured_half,
                         int max_iterations, double epsilon) {
  const float side = MeanSide(corners);
  const int half = MarkerCornerHalfWindow(side, cells, configured_half);
  const float reach = static_cast<float>(CellHalfWindow(side, cells, configured_half));
  for (auto& c : corners) c = RefineCorner(grey, c, half, max_iterations, epsilon, reach);
}

}  // namespace arucotag::internal

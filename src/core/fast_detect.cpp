// Fast path of Detect. cv::aruco::detectMarkers thresholds the whole frame with three window sizes
// (3, 13 and 23 px) and traces every contour of each binary image; on a cluttered 1080p frame that
// is about 70% of its instructions (callgrind). Here each scale gets one window, and the larger
// windows run on a downscaled frame, where they cost a quarter or a sixteenth:
// - level 0 (full resolution), 7 px window: small and sharp markers down to cv::aruco's smallest,
//   searched in horizontal strips, one per core;
// - level 1 (half resolution), 11 px window (22 px of the frame): what cv::aruco's 13 and 23 px
//   windows add, i.e. blurred and low-contrast markers, and markers across a strip boundary;
// - level 2 (quarter resolution), 5 px window: large markers, cheaply enough to run on every frame
//   while tracking.
// Each candidate is decoded on the full-resolution frame the way cv::aruco decodes it (perspective
// removal, Otsu, border bits, dictionary look-up). For the edge-fit refinement, which keeps its
// start where it cannot measure an edge, each marker's starting corners are then re-derived as
// cv::aruco's own (its three windows, on a small window around the marker), so the result is the
// full search's; for cv::aruco's sub-pixel refinement any nearby start converges to the same corner.
//
// With tracking, a frame is searched only around the markers of the previous frame, at level 2
// everywhere, in a band along the image edge the scene moves in from, and in one of
// `full_search_interval` rolling strips: a small marker that appears elsewhere is found within that
// many frames. A frame that does not look like the next one of the same stream (other size, other
// content, most tracked markers missing, nothing tracked) is searched whole.
#include "fast_detect.hpp"

#include "decode_small.hpp"

#include <algorithm>
#include <cfloat>
#include <cmath>
#include <numeric>

#include <opencv2/core/hal/intrin.hpp>
#include <opencv2/imgproc.hpp>
#include <opencv2/imgproc/imgproc_c.h>  // cvFindContours: contours in one arena, not a vector each

namespace arucotag::internal {

namespace {

constexpr int kLevels = 3;  // full, half and quarter resolution

// One threshold window per level, and the smallest marker side (px at that level) a reduced level
// looks for: below it the finer level's contour is the one to trust.
struct LevelSearch {
  int window;
  int min_side;
};
constexpr LevelSearch kLevelSearch[kLevels] = {{7, 0}, {11, 6}, {5, 12}};
constexpr int kCoarseLevel = 2;  // searched over the whole frame on every frame, also when tracking
// Smallest side (px at level 1) from which a marker is reliably found there; level-0 strips overlap
// by enough to hold anything smaller whole.
constexpr int kReliableSideLevel1 = 12;
constexpr double kSceneChange = 12.0;  // mean |grey difference| of 1/32-scale thumbnails: another image
// Frames a marker that stopped decoding (too small, blurred, occluded for a moment) keeps its search
// region: it is found again the first frame it decodes, not when the rolling strip comes round.
constexpr int kCoastFrames = 15;

struct Pyramid {
  std::array<cv::Mat, kLevels> images;
  void Build(const cv::Mat& grey) {
    images[0] = grey;
    for (int l = 1; l < kLevels; ++l) {
      cv::resize(images[l - 1], images[l], cv::Size(images[l - 1].cols / 2, images[l - 1].rows / 2), 0, 0,
                 cv::INTER_AREA);
    }
  }
};

double Scale(int level) { return 1.0 / (1 << level); }

// Level pixel -> full-resolution pixel (pixel centres at integers: a level-l pixel covers 2^l
// full-resolution pixels).
cv::Point2f ToFull(const cv::Point2f& p, int level) {
  const float s = static_cast<float>(1 << level);
  return (p + cv::Point2f(0.5f, 0.5f)) * s - cv::Point2f(0.5f, 0.5f);
}

struct SearchTask {
  int level = 0;
  int window = 0;
  cv::Rect roi;  // level pixels
  int min_perimeter = 0, max_perimeter = 0;  // level pixels
};

// cv::adaptiveThreshold(src, MEAN_C, THRESH_BINARY_INV, W, constant) written into `out`, which
// gets a 1-pixel zero frame around it (what cv::findContours pads with). Same decision as OpenCV:
// black (255) where src + floor(constant) <= round(box mean), edges replicated. The box sums are
// 16-bit, row by row, so the compiler vectorises every loop; OpenCV's version compares through a
// per-pixel table look-up.
template <int W>
void BoxThreshold(const cv::Mat& src, int delta, cv::Mat& out) {
  constexpr int r = W / 2;
  constexpr int area = W * W;
  const int w = src.cols, h = src.rows;
  out.create(h + 2, w + 2, CV_8UC1);
  out.row(0).setTo(0);
  out.row(h + 1).setTo(0);
  std::vector<uint16_t> cols(w + 2 * r, 0);
  uint16_t* col = cols.data() + r;
  const auto row = [&](int y) { return src.ptr<uchar>(std::min(std::max(y, 0), h - 1)); };
  for (int k = -r; k <= r; ++k) {
    const uchar* in = row(k);
    for (int x = 0; x < w; ++x) col[x] = static_cast<uint16_t>(col[x] + in[x]);
  }
  for (int y = 0; y < h; ++y) {
    if (y > 0) {
      const uchar* add = row(y + r);
      const uchar* sub = row(y - r - 1);
      for (int x = 0; x < w; ++x) col[x] = static_cast<uint16_t>(col[x] + add[x] - sub[x]);
    }
    for (int k = 1; k <= r; ++k) {
      col[-k] = col[0];
      col[w - 1 + k] = col[w - 1];
    }
    const uchar* __restrict in = src.ptr<uchar>(y);
    uchar* __restrict dst = out.ptr<uchar>(y + 1);
    dst[0] = 0;
    dst[w + 1] = 0;
    const uint16_t* __restrict c = col - r;
    for (int x = 0; x < w; ++x) {
      uint16_t sum = 0;
      for (int k = 0; k < W; ++k) sum = static_cast<uint16_t>(sum + c[x + k]);
      const uint16_t lhs = static_cast<uint16_t>((in[x] + delta) * (2 * area));
      const uint16_t rhs = static_cast<uint16_t>(2 * sum + area);
      dst[x + 1] = lhs <= rhs ? 255 : 0;
    }
  }
}

void Threshold(const cv::Mat& src, int window, double constant, cv::Mat& out) {
  const int delta = cvFloor(constant);
  // 16-bit headroom: (255 + delta) * 2 * W^2 must fit.
  const bool fits = delta >= 0 && (255 + delta) * 2 * window * window <= 65535;
  if (fits && window == 5) return BoxThreshold<5>(src, delta, out);
  if (fits && window == 7) return BoxThreshold<7>(src, delta, out);
  if (fits && window == 11) return BoxThreshold<11>(src, delta, out);
  cv::Mat binary;
  cv::adaptiveThreshold(src, binary, 255, cv::ADAPTIVE_THRESH_MEAN_C, cv::THRESH_BINARY_INV, window, constant);
  cv::copyMakeBorder(binary, out, 1, 1, 1, 1, cv::BORDER_CONSTANT, cv::Scalar(0));
}

// Quads in a thresholded region (`binary` with its 1-pixel zero frame; `roi` where it lies in its
// level), filtered exactly as cv::aruco's _findMarkerContours filters them, plus: a quad closer than
// `inner` to an edge of the region that is not the image's is dropped (that marker belongs to a
// neighbouring region, or its blob goes on outside). With `near` (level pixels), only contours
// whose bounding box is within `tolerance` of it on every side are fitted.
void QuadsFromBinary(cv::Mat& binary, const cv::Rect& roi, const cv::Size& level_size, const SearchTask& task,
                     int inner, const DetectorConfig& config, std::vector<Quad>& out, const cv::Rect* near = nullptr,
                     int tolerance = 0) {
  CvMat header = cvMat(binary);
  // One arena per thread, emptied (not freed) before each use.
  thread_local const cv::MemStorage storage(cvCreateMemStorage(0));
  cvClearMemStorage(storage);
  CvSeq* first = nullptr;
  cvFindContours(&header, storage, &first, sizeof(CvContour), CV_RETR_LIST, CV_CHAIN_APPROX_NONE, cvPoint(-1, -1));

  // Image border as cv::aruco applies it.
  const int border = task.level == 0 ? config.min_distance_to_border
                                     : std::max(1, static_cast<int>(std::ceil(config.min_distance_to_border *
                                                                              Scale(task.level))));
  const int left = roi.x > 0 ? roi.x + inner : border;
  const int top = roi.y > 0 ? roi.y + inner : border;
  const int right = roi.x + roi.width < level_size.width ? roi.x + roi.width - 1 - inner : level_size.width - 1 - border;
  const int bottom =
      roi.y + roi.height < level_size.height ? roi.y + roi.height - 1 - inner : level_size.height - 1 - border;

  thread_local std::vector<cv::Point> contour, approx;
  for (CvSeq* seq = first; seq; seq = seq->h_next) {
    const int n = seq->total;
    if (n < task.min_perimeter || n > task.max_perimeter) continue;
    const cv::Rect box = reinterpret_cast<CvContour*>(seq)->rect;
    if (near) {
      const cv::Rect b = box + roi.tl();
      if (std::abs(b.x - near->x) > tolerance || std::abs(b.y - near->y) > tolerance ||
          std::abs(b.x + b.width - near->x - near->width) > tolerance ||
          std::abs(b.y + b.height - near->y - near->height) > tolerance) {
        continue;
      }
    }
    // A quad whose bounding box is this thin has a side under cv::aruco's min_corner_distance
    // anyway (and no decodable cells): skip the polygon fit for the clutter's lines and arcs.
    if (16 * std::min(box.width, box.height) < n) continue;
    contour.resize(n);
    cvCvtSeqToArray(seq, contour.data(), CV_WHOLE_SEQ);
    // Likewise a contour enclosing almost nothing (a diagonal line, an arc) cannot be a quad with
    // sides of at least min_corner_distance: a square's area is n^2/16 to n^2/8 in chain steps.
    if (128.0 * std::fabs(cv::contourArea(contour)) < double(n) * n) continue;
    cv::approxPolyDP(contour, approx, n * config.polygonal_approx_accuracy_rate, true);
    if (approx.size() != 4 || !cv::isContourConvex(approx)) continue;
    double min_dist_sq = 1e300;
    for (int j = 0; j < 4; ++j) {
      const cv::Point d = approx[j] - approx[(j + 1) % 4];
      min_dist_sq = std::min(min_dist_sq, double(d.x) * d.x + double(d.y) * d.y);
    }
    const double min_corner = n * config.min_corner_distance_rate;
    if (min_dist_sq < min_corner * min_corner) continue;
    bool outside = false;
    for (auto& p : approx) {
      p += roi.tl();
      outside |= p.x < left || p.y < top || p.x > right || p.y > bottom;
    }
    if (outside) continue;

    Quad quad;
    quad.level = task.level;
    quad.perimeter = static_cast<int>(std::lround(n / Scale(task.level)));
    for (int j = 0; j < 4; ++j) quad.corners[j] = ToFull(cv::Point2f(approx[j]), task.level);
    // Clockwise, as _reorderCandidatesCorners makes it.
    const cv::Point2f d1 = quad.corners[1] - quad.corners[0], d2 = quad.corners[2] - quad.corners[0];
    if (double(d1.x) * d2.y - double(d1.y) * d2.x < 0.0) std::swap(quad.corners[1], quad.corners[3]);
    quad.area = static_cast<float>(cv::contourArea(std::vector<cv::Point2f>(quad.corners.begin(), quad.corners.end())));
    out.push_back(quad);
  }
}

// Quads of one task: its region thresholded (the region's edges replicated, so quads within the
// window's reach of an inner edge are dropped), then QuadsFromBinary.
void FindQuads(const Pyramid& pyramid, const SearchTask& task, const DetectorConfig& config,
               std::vector<Quad>& out) {
  const cv::Mat& level_image = pyramid.images[task.level];
  const cv::Rect roi = task.roi & cv::Rect(0, 0, level_image.cols, level_image.rows);
  if (roi.width < task.window + 2 || roi.height < task.window + 2) return;
  cv::Mat binary;
  Threshold(level_image(roi), task.window, config.adaptive_thresh_constant, binary);
  QuadsFromBinary(binary, roi, level_image.size(), task, task.window / 2 + 2, config, out);
}

// Whether two quads are one candidate for cv::aruco's _filterTooCloseCandidates: their corners (in
// some cyclic order) closer, RMS, than `rate` of the smaller perimeter.
bool TooClose(const Quad& a, const Quad& b, double rate) {
  return CornersWithin(a.corners, b.corners, rate * std::min(a.perimeter, b.perimeter));
}

// cv::aruco's _filterTooCloseCandidates within each pyramid level: of quads too close to each
// other only the biggest is decoded. Quads of different levels are all kept (a coarse quad of a
// noisy marker may be the only good one); duplicates across levels are resolved after decoding.
std::vector<Quad> MergeQuads(std::vector<Quad> quads, double rate) {
  const size_t n = quads.size();
  std::vector<cv::Point2f> centre(n);
  for (size_t i = 0; i < n; ++i) {
    centre[i] = (quads[i].corners[0] + quads[i].corners[1] + quads[i].corners[2] + quads[i].corners[3]) * 0.25f;
  }
  std::vector<size_t> order(n);
  std::iota(order.begin(), order.end(), 0);
  std::sort(order.begin(), order.end(), [&](size_t a, size_t b) { return centre[a].x < centre[b].x; });
  std::vector<size_t> parent(n);
  std::iota(parent.begin(), parent.end(), 0);
  const auto root = [&](size_t i) {
    while (parent[i] != i) i = parent[i] = parent[parent[i]];
    return i;
  };
  for (size_t a = 0; a < n; ++a) {
    const size_t i = order[a];
    for (size_t b = a + 1; b < n; ++b) {
      const size_t j = order[b];
      // The centres differ by the mean corner offset, which is at most the RMS one.
      if (centre[j].x - centre[i].x > rate * quads[i].perimeter) break;
      if (quads[i].level != quads[j].level) continue;
      if (std::abs(centre[j].y - centre[i].y) > rate * std::min(quads[i].perimeter, quads[j].perimeter)) continue;
      if (TooClose(quads[i], quads[j], rate)) parent[root(i)] = root(j);
    }
  }
  std::vector<int> best(n, -1);
  for (size_t i = 0; i < n; ++i) {
    const size_t r = root(i);
    const int k = best[r];
    if (k < 0 || quads[i].area >= quads[k].area) best[r] = static_cast<int>(i);
  }
  std::vector<Quad> merged;
  for (size_t i = 0; i < n; ++i) {
    if (best[i] >= 0) merged.push_back(quads[best[i]]);
  }
  return merged;
}

// Bits set in x (no popcnt instruction in the x86-64 baseline this is built for).
inline int PopCount(uint64_t x) {
  x = x - ((x >> 1) & 0x5555555555555555ULL);
  x = (x & 0x3333333333333333ULL) + ((x >> 2) & 0x3333333333333333ULL);
  x = (x + (x >> 4)) & 0x0f0f0f0f0f0f0f0fULL;
  return static_cast<int>((x * 0x0101010101010101ULL) >> 56);
}

// A dictionary's codes (each rotation) as 64-bit words, so that a look-up is one XOR and a
// popcount per rotation instead of one per byte. Cached per thread for the last dictionary seen.
struct DictionaryCodes {
  const uchar* data = nullptr;
  int rows = 0, cols = 0;
  uint64_t checksum = 0;
  std::vector<uint64_t> code;   // 4 per marker: rotations 0..3
};

const DictionaryCodes& CodesOf(const cv::aruco::Dictionary& dictionary) {
  thread_local DictionaryCodes cache;
  const cv::Mat& list = dictionary.bytesList;
  const int nbytes = (dictionary.markerSize * dictionary.markerSize + 7) / 8;
  uint64_t checksum = 0;
  for (int m = 0; m < list.rows; m += std::max(1, list.rows / 16)) {
    for (int k = 0; k < 4 * nbytes; ++k) checksum = checksum * 131 + list.ptr(m)[k];
  }
  if (cache.data == list.data && cache.rows == list.rows && cache.cols == list.cols && cache.checksum == checksum) {
    return cache;
  }
  cache = DictionaryCodes();
  cache.data = list.data;
  cache.rows = list.rows;
  cache.cols = list.cols;
  cache.checksum = checksum;
  // Every predefined dictionary (the only ones a Detector builds) has at most 7x7 = 49 bits.
  CV_Assert(nbytes <= 8);
  cache.code.resize(static_cast<size_t>(list.rows) * 4);
  for (int m = 0; m < list.rows; ++m) {
    for (int r = 0; r < 4; ++r) {
      uint64_t v = 0;
      for (int k = 0; k < nbytes; ++k) v = (v << 8) | list.ptr(m)[r * nbytes + k];
      cache.code[static_cast<size_t>(m) * 4 + r] = v;
    }
  }
  return cache;
}

// cv::aruco's _extractBits + _getBorderErrors + Dictionary::identify for a black marker, without
// its per-candidate allocations: the canonical image is sampled straight from the homography
// (nearest pixel, as warpPerspective INTER_NEAREST; outside the frame reads 0 like its constant
// border), Otsu's threshold is OpenCV's formula, cells are majority votes of their inner pixels,
// and the look-up compares the packed bits with the dictionary's four rotations as identify does.
bool Identify(const cv::Mat& grey, const std::array<cv::Point2f, 4>& corners, const cv::aruco::Dictionary& dictionary,
              const cv::aruco::DetectorParameters& p, int& id, int& rotation) {
  constexpr int kMaxCells = 16;  // 14x14 is the largest predefined dictionary with its border
  const int marker_size = dictionary.markerSize;
  const int with_borders = marker_size + 2 * p.markerBorderBits;
  if (with_borders > kMaxCells) return false;
  const int cell = p.perspectiveRemovePixelPerCell;
  const int margin = static_cast<int>(p.perspectiveRemoveIgnoredMarginPerCell * cell);
  const int size = with_borders * cell;
  // Canonical pixel (x, y) is (u, v) = (x, y) / (size - 1) of the unit square.
  const cv::Matx33d h = SquareToQuad(corners) * cv::Matx33d(1.0 / (size - 1), 0, 0, 0, 1.0 / (size - 1), 0, 0, 0, 1);
  thread_local std::vector<uchar> canonical;
  canonical.resize(static_cast<size_t>(size) * size);
  const int cols = grey.cols, rows = grey.rows;
  const uchar* pixels = grey.data;
  const size_t step = grey.step;
  for (int y = 0; y < size; ++y) {
    const double x0 = h(0, 1) * y + h(0, 2), y0 = h(1, 1) * y + h(1, 2), w0 = h(2, 1) * y + h(2, 2);
    uchar* out = &canonical[static_cast<size_t>(y) * size];
    for (int x = 0; x < size; ++x) {
      double w = w0 + h(2, 0) * x;
      w = w ? 1.0 / w : 0.0;
      const int sx = cvRound((x0 + h(0, 0) * x) * w);
      const int sy = cvRound((y0 + h(1, 0) * x) * w);
      out[x] = (unsigned(sx) < unsigned(cols) && unsigned(sy) < unsigned(rows)) ? pixels[sy * step + sx] : 0;
    }
  }

  uchar bits[kMaxCells][kMaxCells] = {};
  // Spread of the inner part (half a cell trimmed): too flat means all one colour, no Otsu.
  double sum = 0.0, sum_sq = 0.0;
  for (int y = cell / 2; y < size - cell / 2; ++y) {
    for (int x = cell / 2; x < size - cell / 2; ++x) {
      const double v = canonical[static_cast<size_t>(y) * size + x];
      sum += v;
      sum_sq += v * v;
    }
  }
  const double n_inner = double(size - 2 * (cell / 2)) * (size - 2 * (cell / 2));
  const double mean = sum / n_inner;
  const double stddev = std::sqrt(std::max(0.0, sum_sq / n_inner - mean * mean));
  if (stddev < p.minOtsuStdDev) {
    for (auto& row : bits) std::fill(std::begin(row), std::end(row), mean > 127 ? 1 : 0);
  } else {
    int histogram[256] = {0};
    for (uchar v : canonical) ++histogram[v];
    // OpenCV's getThreshVal_Otsu_8u.
    const double scale = 1.0 / canonical.size();
    double mu = 0.0;
    for (int i = 0; i < 256; ++i) mu += i * double(histogram[i]);
    mu *= scale;
    double mu1 = 0.0, q1 = 0.0, max_sigma = 0.0;
    int threshold = 0;
    for (int i = 0; i < 256; ++i) {
      const double p_i = histogram[i] * scale;
      mu1 *= q1;
      q1 += p_i;
      const double q2 = 1.0 - q1;
      if (std::min(q1, q2) < FLT_EPSILON || std::max(q1, q2) > 1.0 - FLT_EPSILON) continue;
      mu1 = (mu1 + i * p_i) / q1;
      const double mu2 = (mu - q1 * mu1) / q2;
      const double sigma = q1 * q2 * (mu1 - mu2) * (mu1 - mu2);
      if (sigma > max_sigma) {
        max_sigma = sigma;
        threshold = i;
      }
    }
    const int inner = cell - 2 * margin;
    for (int y = 0; y < with_borders; ++y) {
      for (int x = 0; x < with_borders; ++x) {
        int white = 0;
        for (int v = 0; v < inner; ++v) {
          const uchar* px = &canonical[static_cast<size_t>(y * cell + margin + v) * size + x * cell + margin];
          for (int u = 0; u < inner; ++u) white += px[u] > threshold;
        }
        bits[y][x] = white > inner * inner / 2;
      }
    }
  }
  int border_errors = 0;
  const int b = p.markerBorderBits;
  for (int y = 0; y < with_borders; ++y) {
    for (int k = 0; k < b; ++k) border_errors += bits[y][k] + bits[y][with_borders - 1 - k];
  }
  for (int x = b; x < with_borders - b; ++x) {
    for (int k = 0; k < b; ++k) border_errors += bits[k][x] + bits[with_borders - 1 - k][x];
  }
  if (border_errors > static_cast<int>(marker_size * marker_size * p.maxErroneousBitsInBorderRate)) return false;

  // Dictionary::getByteListFromBits (rotation 0 only, which is all identify compares) + identify.
  const int nbytes = (marker_size * marker_size + 7) / 8;
  uchar packed[(kMaxCells * kMaxCells + 7) / 8] = {};
  int bit = 0, byte = 0;
  for (int y = 0; y < marker_size; ++y) {
    for (int x = 0; x < marker_size; ++x) {
      packed[byte] = static_cast<uchar>((packed[byte] << 1) | bits[y + b][x + b]);
      if (++bit == 8) {
        bit = 0;
        ++byte;
      }
    }
  }
  const int max_correction = static_cast<int>(double(dictionary.maxCorrectionBits) * p.errorCorrectionRate);
  const DictionaryCodes& codes = CodesOf(dictionary);
  uint64_t candidate = 0;
  for (int k = 0; k < nbytes; ++k) candidate = (candidate << 8) | packed[k];
  const uint64_t* code = codes.code.data();
  for (int m = 0; m < dictionary.bytesList.rows; ++m, code += 4) {
    int best = marker_size * marker_size + 1, best_rotation = -1;
    for (int r = 0; r < 4; ++r) {
      const int distance = PopCount(code[r] ^ candidate);
      if (distance < best) {
        best = distance;
        best_rotation = r;
      }
    }
    if (best <= max_correction) {
      id = m;
      rotation = best_rotation;
      return true;
    }
  }
  return false;
}

// cv::cornerSubPix (zero zone off) for one point, same iteration, stopping rule and fallback, in
// float and 4-wide SIMD: OpenCV's version, in double with a getRectSubPix call per iteration, is
// the main cost of a frame with many markers. Converges to the same point within a few
// thousandths of a pixel.
cv::Point2f RefineCorner(const cv::Mat& grey, cv::Point2f start, int half, int max_iterations, double epsilon) {
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
  // Too far from the start: poor convergence, keep the start (OpenCV's rule).
  if (std::fabs(c.x - start.x) > half || std::fabs(c.y - start.y) > half) c = start;
  return c;
}

int MaxDim(const cv::Size& s) { return std::max(s.width, s.height); }

// A task at `level` over `roi` (level pixels) with cv::aruco's perimeter limits (rates of the full
// frame), at reduced levels nothing below their min_side.
SearchTask MakeTask(const DetectorConfig& config, const cv::Size& frame, int level, const cv::Rect& roi,
                    int window = 0) {
  SearchTask task;
  task.level = level;
  task.window = window > 0 ? window : kLevelSearch[level].window;
  task.roi = roi;
  const double full = MaxDim(frame);
  task.min_perimeter = static_cast<int>(config.min_marker_perimeter_rate * full * Scale(level));
  task.min_perimeter = std::max(task.min_perimeter, 4 * kLevelSearch[level].min_side);
  task.max_perimeter = static_cast<int>(config.max_marker_perimeter_rate * full * Scale(level));
  return task;
}

cv::Rect ToLevel(const cv::Rect& full, int level) {
  const int s = 1 << level;
  return cv::Rect(full.x / s, full.y / s, (full.x + full.width + s - 1) / s - full.x / s,
                  (full.y + full.height + s - 1) / s - full.y / s);
}

// Rows a level-0 strip reaches past its neighbour, so that every quad level 1 may miss lies wholly
// in one strip: a convex quad spans at most half its contour length (a 45-degree square a little
// less); contour lengths scale with resolution; plus 5% for pixel steps and the rows the threshold
// window reaches on each side of the cut.
int StripOverlap() {
  const double unseen_length = 4.0 * kReliableSideLevel1 * 2 * 1.05;
  return static_cast<int>(std::ceil(0.5 * unseen_length)) + 2 * (kLevelSearch[0].window / 2 + 2) + 2;
}

// Tasks searching the full-resolution rectangle `region` at levels [first, last]; level 0 split into
// `strips` overlapping horizontal strips (one per core for a whole frame).
void AddRegion(const DetectorConfig& config, const cv::Size& frame, const cv::Rect& region, int first, int last,
               int strips, std::vector<SearchTask>& tasks) {
  for (int level = first; level <= last; ++level) {
    if (level > 0) {
      tasks.push_back(MakeTask(config, frame, level, ToLevel(region, level)));
      continue;
    }
    const int overlap = StripOverlap();
    const int count = std::max(1, std::min(strips, region.height / std::max(1, 2 * overlap)));
    for (int k = 0; k < count; ++k) {
      const int top = region.y + region.height * k / count;
      const int bottom = k + 1 < count ? region.y + region.height * (k + 1) / count + overlap : region.y + region.height;
      tasks.push_back(MakeTask(config, frame, 0, cv::Rect(region.x, top, region.width, bottom - top)));
    }
  }
}

void RunTasks(const Pyramid& pyramid, const std::vector<SearchTask>& tasks, const DetectorConfig& config,
              std::vector<Quad>& quads) {
  std::vector<std::vector<Quad>> per_task(tasks.size());
  cv::parallel_for_(cv::Range(0, static_cast<int>(tasks.size())), [&](const cv::Range& range) {
    for (int i = range.start; i < range.end; ++i) FindQuads(pyramid, tasks[i], config, per_task[i]);
  });
  for (auto& q : per_task) quads.insert(quads.end(), q.begin(), q.end());
}

cv::Point2f Centre(const std::array<cv::Point2f, 4>& c) { return (c[0] + c[1] + c[2] + c[3]) * 0.25f; }

float Side(const std::array<cv::Point2f, 4>& c) {
  float s = 0.0f;
  for (int i = 0; i < 4; ++i) s += static_cast<float>(cv::norm(c[i] - c[(i + 1) % 4]));
  return s / 4.0f;
}

cv::Rect Bounds(const std::array<cv::Point2f, 4>& c) {
  return cv::boundingRect(std::vector<cv::Point2f>(c.begin(), c.end()));
}

cv::Rect Grow(const cv::Rect& r, int pad, const cv::Size& frame) {
  return cv::Rect(r.x - pad, r.y - pad, r.width + 2 * pad, r.height + 2 * pad) & cv::Rect(cv::Point(0, 0), frame);
}

// The quads cv::aruco's candidate search (every configured threshold window, same contour filters)
// finds around `corners` (full resolution), run on a small window around them: those whose
// bounding box matches the quad's within a few pixels, appended to `found`. Box means come from an
// integral image of the neighbourhood (frame edges replicated as cv::adaptiveThreshold does), so
// the binary image is the whole frame's there. Only a ring around the quad's outline is
// thresholded: its inside is set black, which leaves the outer contour as it is and skips tracing
// the marker's bits.
void OpenCvQuadsNear(const Pyramid& pyramid, const DetectorConfig& config, const std::array<cv::Point2f, 4>& corners,
                     std::vector<Quad>& found) {
  const cv::Mat& grey = pyramid.images[0];
  const cv::Size frame = grey.size();
  const cv::Rect whole(cv::Point(0, 0), frame);
  const cv::Rect box = Bounds(corners);
  const float side = Side(corners);
  // Outlines of one marker at different windows lie within a few pixels of each other.
  const int tolerance = std::max(3, static_cast<int>(std::ceil(0.06f * side)));
  const cv::Rect roi = Grow(box, tolerance + 2, frame);
  const int reach = (config.adaptive_thresh_win_size_max | 1) / 2 + 1;
  const cv::Rect ext(roi.x - reach, roi.y - reach, roi.width + 2 * reach, roi.height + 2 * reach);
  const cv::Rect inside = ext & whole;
  thread_local cv::Mat patch, sums, binary;
  cv::copyMakeBorder(grey(inside), patch, inside.y - ext.y, ext.y + ext.height - inside.y - inside.height,
                     inside.x - ext.x, ext.x + ext.width - inside.x - inside.width, cv::BORDER_REPLICATE);
  cv::integral(patch, sums, CV_32S);

  // Per row of the region, the span deep inside the marker (its quad shrunk towards the centre).
  const cv::Point2f centre = Centre(corners);
  const float shrink = 1.0f - 2.0f * (tolerance + 2) / std::max(side, 1.0f);
  std::vector<cv::Point2f> core;
  for (const auto& c : corners) core.push_back(centre + (c - centre) * shrink);
  std::vector<std::pair<int, int>> span(roi.height, {1, 0});
  if (shrink > 0.2f) {
    for (int yy = 0; yy < roi.height; ++yy) {
      const float y = static_cast<float>(roi.y + yy);
      float lo = 1e30f, hi = -1e30f;
      for (int e = 0; e < 4; ++e) {
        const cv::Point2f a = core[e], b = core[(e + 1) % 4];
        if ((a.y - y) * (b.y - y) > 0.0f || a.y == b.y) continue;
        const float x = a.x + (b.x - a.x) * (y - a.y) / (b.y - a.y);
        lo = std::min(lo, x);
        hi = std::max(hi, x);
      }
      if (lo <= hi) span[yy] = {static_cast<int>(std::ceil(lo)) - roi.x, static_cast<int>(std::floor(hi)) - roi.x};
    }
  }

  const int delta = cvFloor(config.adaptive_thresh_constant);
  for (int window = config.adaptive_thresh_win_size_min; window <= config.adaptive_thresh_win_size_max;
       window += config.adaptive_thresh_win_size_step) {
    const int w = window | 1;  // cv::aruco makes even windows odd
    const int r = w / 2, area = w * w;
    binary.create(roi.height + 2, roi.width + 2, CV_8UC1);
    binary.setTo(0);
    for (int yy = 0; yy < roi.height; ++yy) {
      // Row yy of the region is row yy + reach of the patch; the integral has one more row/column.
      const int* top = sums.ptr<int>(yy + reach - r);
      const int* bottom = sums.ptr<int>(yy + reach + r + 1);
      const uchar* in = patch.ptr<uchar>(yy + reach) + reach;
      uchar* out = binary.ptr<uchar>(yy + 1) + 1;
      const int* __restrict b0 = bottom + reach - r;
      const int* __restrict b1 = bottom + reach + r + 1;
      const int* __restrict t0 = top + reach - r;
      const int* __restrict t1 = top + reach + r + 1;
      for (int xx = 0; xx < roi.width; ++xx) {
        const int sum = b1[xx] - b0[xx] - t1[xx] + t0[xx];
        out[xx] = (in[xx] + delta) * 2 * area <= 2 * sum + area ? 255 : 0;
      }
      const auto [lo, hi] = span[yy];
      if (lo <= hi) std::fill(out + std::max(lo, 0), out + std::min(hi, roi.width - 1) + 1, uchar(255));
    }
    QuadsFromBinary(binary, roi, frame, MakeTask(config, frame, 0, roi, w), 1, config, found, &box, tolerance);
  }
}

// The corners cv::aruco would start from for this marker: of the quads its candidate search finds
// there (OpenCvQuadsNear), the biggest of those that coincide with it, as _filterTooCloseCandidates
// keeps it. Corners come back in `decoded`'s order (rotation already applied); returns false when no
// configured window gives a quad there (a marker only the reduced levels see).
bool CornersAsOpenCv(const Pyramid& pyramid, const DetectorConfig& config, Quad& decoded) {
  thread_local std::vector<Quad> found;
  found.clear();
  OpenCvQuadsNear(pyramid, config, decoded.corners, found);
  const Quad* best = nullptr;
  for (const Quad& q : found) {
    if (TooClose(q, decoded, config.min_marker_distance_rate) && (!best || q.area > best->area)) best = &q;
  }
  if (!best) return false;
  int shift = 0;
  double closest = 1e300;
  for (int fc = 0; fc < 4; ++fc) {
    double d = 0.0;
    for (int c = 0; c < 4; ++c) d += cv::norm(best->corners[(c + fc) % 4] - decoded.corners[c]);
    if (d < closest) {
      closest = d;
      shift = fc;
    }
  }
  Quad exact = *best;
  for (int c = 0; c < 4; ++c) exact.corners[c] = best->corners[(c + shift) % 4];
  decoded = exact;
  return true;
}

// Decodes a small quad cv::aruco's reading rejected (`decoded` and `id` set on success). At this
// size a one-pixel difference of the contour flips cells of its 4-px-per-cell reading, and
// cv::aruco's windows (3, 13, 23 px) trace slightly different contours than this search's: those
// are traced on the quad's neighbourhood and read the same way first, so that every marker the full
// search decodes is decoded here too. What still fails gets the second-chance decoder, on this
// contour and on cv::aruco's (`second_chance` set: cv::aruco has no corners of its own there).
bool DecodeSmallQuad(const Pyramid& pyramid, const DetectorConfig& config, const cv::aruco::Dictionary& dictionary,
                     const cv::aruco::DetectorParameters& p, const Quad& quad, Quad& decoded, int& id,
                     bool& second_chance) {
  const cv::Mat& grey = pyramid.images[0];
  std::vector<Quad> traced;
  OpenCvQuadsNear(pyramid, config, quad.corners, traced);
  // Of quads that coincide, cv::aruco reads only the biggest (_filterTooCloseCandidates, MergeQuads
  // here); reading every window's contour gives a texture more chances to pass for a code (measured:
  // 17 extra false detections over the test photos with wrong dictionaries). Biggest first.
  std::vector<Quad> local = MergeQuads(std::move(traced), config.min_marker_distance_rate);
  std::sort(local.begin(), local.end(), [](const Quad& a, const Quad& b) { return a.area > b.area; });
  for (const Quad& q : local) {
    int rotation = 0;
    if (!Identify(grey, q.corners, dictionary, p, id, rotation)) continue;
    decoded = q;
    std::rotate(decoded.corners.begin(), decoded.corners.begin() + 4 - rotation, decoded.corners.end());
    // Read on contours cv::aruco may never have read: held to the second chance's standard.
    if (!PatternExplainsPixels(grey, dictionary, id, p.markerBorderBits, decoded.corners)) continue;
    return true;
  }
  local.insert(local.begin(), quad);
  for (const Quad& q : local) {
    SmallMarker marker;
    if (!DecodeSmall(grey, q.corners, dictionary, p.markerBorderBits, p.detectInvertedMarker, marker)) continue;
    decoded = q;
    decoded.corners = marker.corners;
    id = marker.id;
    second_chance = true;
    return true;
  }
  return false;
}

// Decodes every candidate (small ones cv::aruco's reading rejects with DecodeSmallQuad), keeps one
// marker where several levels found the same one (cv::aruco's reading over the second chance, then
// the finest level's, then the biggest), and refines: kSubpix with RefineCorner; for kEdge the
// corners cv::aruco would start from (CornersAsOpenCv) are returned for Detect's edge fit, except
// for a marker no full-resolution window finds (reduced levels only), whose scaled corners get
// RefineCorner first so the edge fit starts within its reach, and a second-chance marker, whose
// decoder's corners are the edge fit's start (a 5 px cornerSubPix window spans most of it).
std::vector<Found> Decode(const Pyramid& pyramid, const std::vector<Quad>& quads, const DetectorConfig& config,
                          const cv::aruco::Dictionary& dictionary, const cv::aruco::DetectorParameters& p) {
  const cv::Mat& grey = pyramid.images[0];
  std::vector<int> ids(quads.size(), -1);
  std::vector<Quad> decoded(quads);
  std::vector<char> second_chance(quads.size(), 0);
  cv::parallel_for_(cv::Range(0, static_cast<int>(quads.size())), [&](const cv::Range& range) {
    for (int i = range.start; i < range.end; ++i) {
      int id = -1, rotation = 0;
      if (!Identify(grey, quads[i].corners, dictionary, p, id, rotation)) continue;
      auto& corners = decoded[i].corners;
      std::rotate(corners.begin(), corners.begin() + 4 - rotation, corners.end());
      ids[i] = id;
    }
  });
  // Small quads left over, except the cells of markers already read and the outlines around them
  // (their quiet zones): every marker of a few cells per side has several, and a second look at
  // each costs more than the search.
  std::vector<int> fragile;
  for (size_t i = 0; i < quads.size(); ++i) {
    if (ids[i] >= 0 || !(Side(quads[i].corners) < kSmallCandidateMaxSide)) continue;
    const cv::Point2f centre = Centre(quads[i].corners);
    const std::vector<cv::Point2f> outline(quads[i].corners.begin(), quads[i].corners.end());
    bool overlaps = false;
    for (size_t k = 0; k < quads.size() && !overlaps; ++k) {
      if (ids[k] < 0) continue;
      const auto& c = decoded[k].corners;
      overlaps = decoded[k].area > quads[i].area
                     ? cv::pointPolygonTest(std::vector<cv::Point2f>(c.begin(), c.end()), centre, false) > 0.0
                     : cv::pointPolygonTest(outline, Centre(c), false) > 0.0;
    }
    if (!overlaps) fragile.push_back(static_cast<int>(i));
  }
  cv::parallel_for_(cv::Range(0, static_cast<int>(fragile.size())), [&](const cv::Range& range) {
    for (int f = range.start; f < range.end; ++f) {
      const int i = fragile[f];
      int id = -1;
      bool second = false;
      if (DecodeSmallQuad(pyramid, config, dictionary, p, quads[i], decoded[i], id, second)) {
        ids[i] = id;
        second_chance[i] = second;
      }
    }
  });
  std::vector<size_t> kept;
  for (size_t i = 0; i < quads.size(); ++i) {
    if (ids[i] < 0) continue;
    bool duplicate = false;
    for (size_t& k : kept) {
      if (ids[k] != ids[i] || !TooClose(decoded[k], decoded[i], p.minMarkerDistanceRate)) continue;
      const Quad &a = decoded[i], &b = decoded[k];
      const bool better = second_chance[i] != second_chance[k]
                              ? !second_chance[i]
                              : a.level < b.level || (a.level == b.level && a.area > b.area);
      if (better) k = i;
      duplicate = true;
      break;
    }
    if (!duplicate) kept.push_back(i);
  }
  const bool subpix = config.corner_refinement == CornerRefinement::kSubpix;
  std::vector<Found> found(kept.size());
  cv::parallel_for_(cv::Range(0, static_cast<int>(kept.size())), [&](const cv::Range& range) {
    for (int i = range.start; i < range.end; ++i) {
      Quad q = decoded[kept[i]];
      const bool second = second_chance[kept[i]];
      // cornerSubPix lands within a few hundredths of a pixel from any start a pixel or two away;
      // the edge fit keeps its start where it cannot measure an edge, so it gets cv::aruco's.
      const bool exact = !subpix && (second || CornersAsOpenCv(pyramid, config, q));
      found[i].id = ids[kept[i]];
      found[i].corners = q.corners;
      if (exact) continue;
      for (auto& c : found[i].corners) {
        c = RefineCorner(grey, c, p.cornerRefinementWinSize, p.cornerRefinementMaxIterations,
                         p.cornerRefinementMinAccuracy);
      }
    }
  });
  return found;
}

// Pixels thresholded and traced, at their level's resolution.
int Pixels(const std::vector<SearchTask>& tasks) {
  int pixels = 0;
  for (const auto& t : tasks) pixels += t.roi.area();
  return pixels;
}

std::vector<Found> Search(const Pyramid& pyramid, const std::vector<SearchTask>& tasks, const DetectorConfig& config,
                          const cv::aruco::Dictionary& dictionary, const cv::aruco::DetectorParameters& p,
                          FrameReport& report) {
  std::vector<Quad> quads;
  RunTasks(pyramid, tasks, config, quads);
  quads = MergeQuads(std::move(quads), config.min_marker_distance_rate);
  report.candidates = static_cast<int>(quads.size());
  report.searched_pixels = Pixels(tasks);
  return Decode(pyramid, quads, config, dictionary, p);
}

std::vector<Found> FullSearch(const Pyramid& pyramid, const DetectorConfig& config,
                              const cv::aruco::Dictionary& dictionary, const cv::aruco::DetectorParameters& p,
                              FrameReport& report) {
  const cv::Size frame = pyramid.images[0].size();
  std::vector<SearchTask> tasks;
  AddRegion(config, frame, cv::Rect(cv::Point(0, 0), frame), 0, kLevels - 1, std::max(1, cv::getNumThreads()), tasks);
  report.full_search = true;
  return Search(pyramid, tasks, config, dictionary, p, report);
}

cv::Mat Thumbnail(const Pyramid& pyramid) {
  cv::Mat thumb;
  const cv::Mat& coarse = pyramid.images[kLevels - 1];
  cv::resize(coarse, thumb, cv::Size(std::max(1, coarse.cols / 8), std::max(1, coarse.rows / 8)), 0, 0,
             cv::INTER_AREA);
  return thumb;
}

// Where a tracked marker should be in the next frame (constant velocity).
std::array<cv::Point2f, 4> Predict(const TrackedMarker& m) {
  std::array<cv::Point2f, 4> predicted = m.corners;
  for (auto& p : predicted) p += m.velocity;
  return predicted;
}

// Search tasks of a tracked frame (see the file comment).
std::vector<SearchTask> TrackedTasks(const DetectorConfig& config, const cv::Size& frame,
                                     const std::vector<TrackedMarker>& markers, int strip) {
  std::vector<SearchTask> tasks;
  // Around each tracked marker, at levels 0 and 1 (level 2 covers the whole frame below).
  std::vector<cv::Rect> rois;
  cv::Point2f mean_velocity(0.0f, 0.0f);
  int moving = 0;
  for (const auto& m : markers) {
    const std::array<cv::Point2f, 4> predicted = Predict(m);
    const float side = Side(predicted);
    const int pad = static_cast<int>(std::ceil(0.5f * side + 2.0f * cv::norm(m.velocity) + 4.0f)) +
                    2 * (kLevelSearch[1].window / 2 + 2);
    const cv::Rect roi = Grow(Bounds(predicted), pad, frame);
    if (!roi.empty()) rois.push_back(roi);
    if (m.missed == 0) {
      mean_velocity += m.velocity;
      ++moving;
    }
  }
  if (moving > 0) mean_velocity *= 1.0f / moving;
  // Overlapping regions become their union: no pixel is thresholded twice.
  for (bool merged = true; merged;) {
    merged = false;
    for (size_t i = 0; i < rois.size() && !merged; ++i) {
      for (size_t j = i + 1; j < rois.size(); ++j) {
        if ((rois[i] & rois[j]).area() > 0) {
          rois[i] |= rois[j];
          rois.erase(rois.begin() + j);
          merged = true;
          break;
        }
      }
    }
  }
  for (const auto& roi : rois) AddRegion(config, frame, roi, 0, 1, 1, tasks);
  tasks.push_back(MakeTask(config, frame, kCoarseLevel, ToLevel(cv::Rect(cv::Point(0, 0), frame), kCoarseLevel)));

  // New markers come in from the edge the scene moves away from. The band is searched at level 1
  // as wide as the largest marker level 2 may miss, and at level 0 as wide as the largest marker
  // level 1 may miss (the strip overlap), each plus two frames of motion.
  const int motion = static_cast<int>(std::ceil(2.0 * cv::norm(mean_velocity)));
  const int wide = 2 * kLevelSearch[kCoarseLevel].min_side * (1 << kCoarseLevel) + 2 * (kLevelSearch[1].window + 4) + motion;
  const int narrow = StripOverlap() + motion;
  const cv::Rect whole(cv::Point(0, 0), frame);
  for (const auto& [width, level] : {std::pair<int, int>{narrow, 0}, std::pair<int, int>{wide, 1}}) {
    if (mean_velocity.x < -0.5f) AddRegion(config, frame, cv::Rect(frame.width - width, 0, width, frame.height) & whole, level, level, 1, tasks);
    if (mean_velocity.x > 0.5f) AddRegion(config, frame, cv::Rect(0, 0, width, frame.height) & whole, level, level, 1, tasks);
    if (mean_velocity.y < -0.5f) AddRegion(config, frame, cv::Rect(0, frame.height - width, frame.width, width) & whole, level, level, 1, tasks);
    if (mean_velocity.y > 0.5f) AddRegion(config, frame, cv::Rect(0, 0, frame.width, width) & whole, level, level, 1, tasks);
  }

  // One rolling strip of the whole search, reaching into the next by the strip overlap.
  const int n = std::max(1, config.full_search_interval);
  const int top = frame.height * strip / n;
  const int bottom = std::min(frame.height, frame.height * (strip + 1) / n + StripOverlap());
  AddRegion(config, frame, cv::Rect(0, top, frame.width, bottom - top), 0, 1, 1, tasks);
  return tasks;
}

// Pairs this frame's markers with the previous frame's by id (nearest predicted centre when an id
// repeats); previous markers not found coast on at their velocity for kCoastFrames.
std::vector<TrackedMarker> Track(const std::vector<Found>& found, const std::vector<TrackedMarker>& previous) {
  std::vector<TrackedMarker> next;
  std::vector<bool> used(previous.size(), false);
  for (const auto& f : found) {
    TrackedMarker t;
    t.id = f.id;
    t.corners = f.corners;
    const cv::Point2f c = Centre(f.corners);
    int best = -1;
    double best_dist = 0.0;
    for (size_t i = 0; i < previous.size(); ++i) {
      if (used[i] || previous[i].id != f.id) continue;
      const double d = cv::norm(Centre(previous[i].corners) + previous[i].velocity - c);
      if (best < 0 || d < best_dist) {
        best = static_cast<int>(i);
        best_dist = d;
      }
    }
    if (best >= 0 && best_dist < 2.0 * Side(f.corners) + 8.0) {
      used[best] = true;
      // A coasting marker's corners were moved on each frame: this is one frame's motion.
      t.velocity = c - Centre(previous[best].corners);
    }
    next.push_back(t);
  }
  for (size_t i = 0; i < previous.size(); ++i) {
    if (used[i] || previous[i].missed >= kCoastFrames) continue;
    TrackedMarker t = previous[i];
    t.corners = Predict(t);
    t.missed += 1;
    next.push_back(t);
  }
  return next;
}

// Whether at least half the markers found in the previous frame, predicted well inside this one,
// are missing: the frame is probably not the next one of the stream (a cut, another camera, an
// unrelated image). One marker that stops decoding for a while is not a reason: it coasts, and its
// region is searched exactly as the full search would search it.
bool MostLost(const std::vector<TrackedMarker>& previous, const std::vector<Found>& found, const cv::Size& size) {
  int expected = 0, lost = 0;
  for (const auto& m : previous) {
    if (m.missed > 0) continue;
    const std::array<cv::Point2f, 4> predicted = Predict(m);
    const float margin = 0.25f * Side(predicted) + 4.0f;
    const cv::Rect box = Bounds(predicted);
    const bool inside = box.x >= margin && box.y >= margin && box.x + box.width <= size.width - margin &&
                        box.y + box.height <= size.height - margin;
    if (!inside) continue;
    ++expected;
    const cv::Point2f c = Centre(predicted);
    const bool seen = std::any_of(found.begin(), found.end(), [&](const Found& f) {
      return f.id == m.id && cv::norm(Centre(f.corners) - c) < 2.0 * Side(predicted) + 8.0;
    });
    lost += !seen;
  }
  return expected > 0 && 2 * lost >= expected;
}

}  // namespace

bool FastPathSupports(const DetectorConfig& config) {
  return config.fast_path && !config.detect_inverted_marker &&
         (config.corner_refinement == CornerRefinement::kSubpix || config.corner_refinement == CornerRefinement::kEdge);
}

std::vector<Found> FastDetect(const cv::Mat& grey, const DetectorConfig& config,
                              const cv::Ptr<cv::aruco::Dictionary>& dictionary,
                              const cv::aruco::DetectorParameters& parameters, TrackingState* state,
                              FrameReport* report) {
  FrameReport local;
  FrameReport& r = report ? *report : local;
  r = FrameReport();
  Pyramid pyramid;
  pyramid.Build(grey);

  const bool tracking = state && config.tracking;
  if (!tracking) return FullSearch(pyramid, config, *dictionary, parameters, r);

  // Copy the state out: detection runs without the lock, so one Detector serves several threads
  // (their frames then interleave, which the checks below turn into full searches).
  std::vector<TrackedMarker> previous;
  cv::Mat previous_thumb;
  bool continuing = false;
  int strip = 0;
  {
    std::lock_guard<std::mutex> lock(state->mutex);
    // Nothing tracked, nothing to gain: a frame after one without markers is searched whole, so a
    // stream without markers costs what single frames cost and a marker that appears is found at once.
    continuing = state->size == grey.size() && state->frames > 0 &&
                 std::any_of(state->markers.begin(), state->markers.end(),
                             [](const TrackedMarker& m) { return m.missed == 0; });
    previous = state->markers;
    previous_thumb = state->thumbnail;
    strip = state->strip;
  }
  const cv::Mat thumb = Thumbnail(pyramid);
  continuing = continuing && previous_thumb.size() == thumb.size() &&
               cv::norm(thumb, previous_thumb, cv::NORM_L1) / thumb.total() < kSceneChange;

  std::vector<Found> found;
  bool full = !continuing;
  if (continuing) {
    found = Search(pyramid, TrackedTasks(config, grey.size(), previous, strip), config, *dictionary, parameters, r);
    full = MostLost(previous, found, grey.size());
  }
  if (full) found = FullSearch(pyramid, config, *dictionary, parameters, r);

  {
    std::lock_guard<std::mutex> lock(state->mutex);
    state->markers = Track(found, previous);
    state->size = grey.size();
    state->thumbnail = thumb;
    state->frames += 1;
    state->strip = full ? 0 : (strip + 1) % std::max(1, config.full_search_interval);
    (full ? state->full_searches : state->tracked_frames) += 1;
  }
  return found;
}

}  // namespace arucotag::internal

// Second-chance decoding of tiny candidates, see decode_small.hpp. False positives are what a
// looser decoder risks, so everything here is stricter than cv::aruco except the sampling: exact
// code match, a whole border, a clear black/white gap, a quiet zone around it and at least a pixel
// per cell. (The quiet-zone checks came after a review measured more wrong-dictionary detections on
// the test photos than cv::aruco's.)
#include "decode_small.hpp"

#include "codes.hpp"
#include "refine_pattern.hpp"

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <iterator>
#include <limits>
#include <numeric>
#include <vector>

#include <opencv2/imgproc.hpp>

#include <arucotag/detector.hpp>
#include <arucotag/refine.hpp>

namespace arucotag::internal {

namespace {

// Pixels whose centre lies within this many cells outside the black square take part in the cell
// estimate (they see its edge cells); the quiet zone they also cover is one more unknown.
constexpr double kCoverageMarginCells = 0.5;
// Ridge weight of the least-squares cell estimate, relative to the mean pixel weight per unknown:
// keeps a cell that no pixel sees mostly (under a pixel wide) near the overall mean.
constexpr double kRidge = 0.02;
// Mean white cell minus mean black cell, grey levels: below it the "bits" are texture or noise.
constexpr double kMinContrast = 20.0;
// Under kMinContrast but not under this, a reading is misframed rather than flat: a square a fraction
// of a cell off mixes ink and paper in its cells, and a dim marker's contrast falls under
// kMinContrast there (test_small_markers' dim tag36h11 renders read 17-23). The other framings are then
// tried. test_small_markers' dim tag36h11 framings with one side far inside: 32 of 108 read when such
// a first reading stopped there, 67 with this bound; 66 with 18, 67 with 12-16 (15 and 16 give bench's
// dim distant set 5 more cell estimates than this bound, and no more markers).
constexpr double kMinMisframedContrast = 17.0;
// A cell is read as white or black when it lies at least this fraction of the contrast from the
// threshold; nearer, it is unknown (an erasure). A marker's cells fall into two clear groups, a
// random patch's values are spread out. At 1.5-2 px per cell under a camera's blur the least-squares
// estimate of a lone white cell among black ones lands near the threshold: tag36h11 markers of
// 13-19 px in bench's distant set had 1-3 such cells and were refused whole.
constexpr double kMinCellMargin = 0.1;
// Unknown cells a reading may leave: as many as keep the chance that a random pattern of the
// other cells matches some code in some rotation under kMaxChanceMatch (the code's other cells
// must all match, and exactly one code and rotation may). DICT_4X4_50 (16 bits, 50 codes) and
// DICT_5X5_100 allow none, as before; tag36h11 (36 bits, 587 codes) and DICT_6X6_250 up to 8.
constexpr double kMaxChanceMatch = 1e-5;
constexpr int kMaxUnknownCells = 8;
// Known cells a reading may still get wrong (a lone 1.5 px cell under blur can land past the margin
// on the wrong side): up to kMaxCorrectedCells, as many as keep the chance that a random pattern of
// the known cells lies that close to some code in some rotation under kMaxChanceCorrected, and only
// when no other code and rotation lies as close. tag36h11 gets 2 with at most 2 cells unknown (chance
// 2.3e-5 with all 36 known; AprilTag 3 corrects 2 by default), 1 with 3-6 unknown, none with more;
// DICT_4X4_50 and DICT_5X5_100 none. The quiet zone and the fitted pattern (PatternExplainsPixels)
// still have to agree. In bench's distant tag36h11 set 5 of the 11-15 px markers read 1-2 cells
// wrong; at the 1e-5 of unknown cells only the 3 with one wrong cell would be read.
constexpr double kMaxChanceCorrected = 1e-4;
constexpr int kMaxCorrectedCells = 2;
// The quiet zone's fitted level must be this fraction of the contrast beyond the threshold, and at
// least this share of a ring kQuietRingCells outside the square on its side of the threshold.
constexpr double kQuietMargin = 0.25;
constexpr double kMinQuietShare = 0.9;
constexpr double kQuietRingCells = 0.6;
// A square that frames a marker a fraction of a cell off, or the outline of its quiet zone, has the
// marker's quiet zone or the background the marker stands on around it: fitted there, that level
// lies between the ink and the paper or not far past them. DecodeSmall's first reading (the contour
// grown by its first step) passes a candidate on to the other framings only with that level within
// this many contrasts of the cells' threshold. Measured over bench's 19 sets and test/data's six
// images (its five real photos and a fuzz frame; 7 scales from 1 to 0.2, with and without a 0.8 px
// blur, 6 dictionaries): the 70 first readings that another framing then read had it within
// -0.25..1.06; 2122 of the 4661 that read nothing lie past this bound (their median 0.94: a
// chessboard square is a dark square on white too), which spares them up to seven more cell
// estimates. A background brighter than the paper by half the contrast, or darker than the ink by as
// much, is still within it.
constexpr double kMaxMisframedQuiet = 1.1;
// Grid steps per cell when locating the black square inside a quiet-zone outline.
constexpr int kProfileStepsPerCell = 8;
// How far (cells) the contour of a black square is pushed outwards before its edges are located
// again from the grey levels: past a one-pixel contour error, within the one-cell quiet zone.
constexpr double kExpandCells = 0.6;
// px: a blurred black square's contour (adaptive threshold, traced through the centres of its edge
// pixels) lies about this far inside its edges; at 2 px per cell that misplaces every cell by a
// third of itself. Measured on bench's distant tag36h11 set (0.8 px blur): cv::aruco's contours of
// 13-24 px markers were 0.6-1.2 px short of the true side.
constexpr double kGrowPx[] = {0.5, 0.8};
// Under this many px per cell the growths go in finer steps and a little further: there 0.3 px is
// over a seventh of a cell, and a reading turns on it. Bench's dim distant set: four 12-16 px markers
// whose contours lay 0.5-2 px inside were read from that contour grown by 0.2 or 0.4 px before the
// other framings, and by none of them from the contour itself; with these steps 2 more markers read
// in the distant set and 2 in the dim one, for 2-5 % more of the fast path's instructions on those
// sets and 2 % on the real photos' clutter (callgrind).
constexpr double kFineGrowMaxPxPerCell = 2.25;
constexpr double kFineGrowPx[] = {0.3, 0.5, 0.7, 0.9};
// px: there, too, the contour grown by this much is the start of one more edge fit, after every
// other framing failed (see DecodeSmall). Bench's dim distant set: 2 more markers read (40 -> 42 of
// 60, AprilTag 3's count at decimate 1), whose candidates' corners lay 0.7-2.2 px from the true ones,
// unevenly.
constexpr double kEdgeStartGrowPx = 0.5;

// Bilinear grey value at (x, y); false outside the frame.
bool Bilinear(const cv::Mat& grey, double x, double y, double& value) {
  if (!(x >= 0.0 && y >= 0.0 && x <= grey.cols - 1.0 && y <= grey.rows - 1.0)) return false;
  if (grey.cols < 2 || grey.rows < 2) return false;  // a one-pixel-wide frame
  value = SampleBilinear(grey, x, y);
  return true;
}

// The image point (x, y) of unit-square coordinates (u, v) of h, in double; returns its w (x and y are
// not finite when w is 0).
double UnitToImage(const cv::Matx33d& h, double u, double v, double& x, double& y) {
  const double w = h(2, 0) * u + h(2, 1) * v + h(2, 2);
  x = (h(0, 0) * u + h(0, 1) * v + h(0, 2)) / w;
  y = (h(1, 0) * u + h(1, 1) * v + h(1, 2)) / w;
  return w;
}

// Grey value at unit-square coordinates (u, v) of the quad whose homography is h. `inside`: the caller
// knows the point maps inside the frame with room for SampleInside (UnitSquareInside), so the bounds
// checks and the clamp are skipped (the same value: there truncation is the floor and the clamp never
// acts).
bool SampleUnit(const cv::Mat& grey, const cv::Matx33d& h, double u, double v, double& value, bool inside = false) {
  double x = 0.0, y = 0.0;
  const double w = UnitToImage(h, u, v, x, y);
  if (inside) {
    value = SampleInside(grey, x, y);
    return true;
  }
  if (std::fabs(w) < 1e-12) return false;
  return Bilinear(grey, x, y, value);
}

cv::Point2f MapUnit(const cv::Matx33d& h, double u, double v) { return ApplyHomography(h, u, v); }

// Whether every point of h's unit square maps into the frame with room for SampleInside: the corners'
// w of one sign (w is affine in u and v, so it keeps that sign over the square, and the square maps
// onto the convex quad of its corners) and their box inside [0, cols - 1) x [0, rows - 1) by a
// margin far above the rounding of the mapping.
bool UnitSquareInside(const cv::Mat& grey, const cv::Matx33d& h) {
  constexpr double kMargin = 1e-3;  // px
  for (const double u : {0.0, 1.0}) {
    for (const double v : {0.0, 1.0}) {
      double x = 0.0, y = 0.0;
      if (!(UnitToImage(h, u, v, x, y) > 1e-9)) return false;
      if (!(x >= kMargin && y >= kMargin && x <= grey.cols - 1 - kMargin && y <= grey.rows - 1 - kMargin)) return false;
    }
  }
  return true;
}

// The quad whose unit square is [u0, u1] x [v0, v1] of h's.
cv::Matx33d SubSquare(const cv::Matx33d& h, double u0, double v0, double u1, double v1) {
  return h * cv::Matx33d(u1 - u0, 0.0, u0, 0.0, v1 - v0, v0, 0.0, 0.0, 1.0);
}

std::array<cv::Point2f, 4> Corners(const cv::Matx33d& h) {
  return {MapUnit(h, 0, 0), MapUnit(h, 1, 0), MapUnit(h, 1, 1), MapUnit(h, 0, 1)};
}

float ShortestSide(const std::array<cv::Point2f, 4>& q) {
  float s = 1e30f;
  for (int i = 0; i < 4; ++i) s = std::min(s, static_cast<float>(cv::norm(q[i] - q[(i + 1) % 4])));
  return s;
}

// The cell index (cy * n + cx, or n * n outside the n x n square) shared by four points in cell
// coordinates, when each of them is in the same cell or all are beyond the same edge of the square
// (each a convex region); -1 otherwise.
int WholeCell(const cv::Point2d& a, const cv::Point2d& b, const cv::Point2d& c, const cv::Point2d& d, int n) {
  const double lo_x = std::min({a.x, b.x, c.x, d.x}), hi_x = std::max({a.x, b.x, c.x, d.x});
  const double lo_y = std::min({a.y, b.y, c.y, d.y}), hi_y = std::max({a.y, b.y, c.y, d.y});
  if (hi_x < 0.0 || hi_y < 0.0 || lo_x >= n || lo_y >= n) return n * n;
  const int cx = FloorInt(lo_x), cy = FloorInt(lo_y);
  if (cx < 0 || cy < 0 || cx >= n || cy >= n || FloorInt(hi_x) != cx || FloorInt(hi_y) != cy) return -1;
  return cy * n + cx;
}

// A pixel's cells and their weights (sixteenths, exact) from CoverageSampleCells's cells, in
// ascending cell order: what CoverageCounts gives, for the pixels it leaves (samples over more than
// three columns or rows of cells).
int CountSampleCells(const cv::Point2d& p00, const cv::Point2d& dx, const cv::Point2d& dy, const cv::Point2d& dxy,
                     int n, int* cells, int* counts) {
  int sample_cells[kCoverageSamples * kCoverageSamples];
  CoverageSampleCells(p00, dx, dy, dxy, n, sample_cells);
  std::sort(std::begin(sample_cells), std::end(sample_cells));
  int found = 0;
  for (int i = 0; i < kCoverageSamples * kCoverageSamples; ++i) {
    if (found == 0 || cells[found - 1] != sample_cells[i]) {
      cells[found] = sample_cells[i];
      counts[found++] = 0;
    }
    ++counts[found - 1];
  }
  return found;
}

thread_local size_t cell_estimates = 0;  // SmallCellEstimates

// The grey level of each of the n x n cells of the black square h maps the unit square onto, by
// least squares over the pixels around it: each pixel is modelled as the area-weighted mean of the
// cells (and the quiet zone) it covers. At 1.25 px per cell no pixel sees a cell alone, and a
// sample at the cell's centre reads half its neighbours; the pixel-area model undoes that mixing.
bool EstimateCells(const cv::Mat& grey, const cv::Matx33d& h, int n, std::vector<double>& cells, double& quiet) {
  ++cell_estimates;
  const int unknowns = n * n + 1;  // the cells, then the quiet zone
  const cv::Matx33d to_unit = h.inv();
  const double margin = kCoverageMarginCells / n;
  const std::array<cv::Point2f, 4> outline = Corners(SubSquare(h, -margin, -margin, 1.0 + margin, 1.0 + margin));
  const cv::Rect box = cv::boundingRect(std::vector<cv::Point2f>(outline.begin(), outline.end())) &
                       cv::Rect(0, 0, grey.cols, grey.rows);
  if (box.width < 2 || box.height < 2) return false;
  // The normal matrix's lower triangle, row a valid (and zeroed) from envelope[a] on only: a cell
  // shares pixels with its neighbours alone, so most of the matrix stays zero, and SolveEnvelope
  // reads none of that. (Zeroing the whole 65 x 65 matrix of tag36h11 was 2 % of Detect on bench's
  // distant sets.)
  thread_local std::vector<double> normal;
  thread_local std::vector<int> envelope;
  normal.resize(static_cast<size_t>(unknowns) * unknowns);
  envelope.resize(static_cast<size_t>(unknowns));
  // The buffers through plain pointers: a thread_local's address is a call to __tls_get_addr in a
  // shared library, which the compiler repeated in the pixel loop (0.6 % of Detect's instructions on
  // the real 640x480 photos).
  double* const lhs = normal.data();
  int* const first = envelope.data();
  for (int a = 0; a < unknowns; ++a) {
    first[a] = a;
    lhs[static_cast<size_t>(a) * unknowns + a] = 0.0;
  }
  std::vector<double> rhs(unknowns, 0.0);
  // The unknowns a pixel covers, ascending, and their weights (at most one per sample).
  int touched[kCoverageSamples * kCoverageSamples], counts[kCoverageSamples * kCoverageSamples];
  double weight[kCoverageSamples * kCoverageSamples];
  // Cell coordinates (unit square x n) of the pixel corners: within a pixel the homography is affine
  // to a ten-thousandth of a cell at these sizes, so each pixel's samples are interpolated between
  // its corners instead of each taking a projective division.
  const int gw = box.width + 1, gh = box.height + 1;
  thread_local std::vector<cv::Point2d> grid;
  grid.resize(static_cast<size_t>(gw) * gh);
  cv::Point2d* const grid_points = grid.data();
  for (int gy = 0; gy < gh; ++gy) {
    for (int gx = 0; gx < gw; ++gx) {
      const cv::Vec3d g = to_unit * cv::Vec3d(box.x + gx - 0.5, box.y + gy - 0.5, 1.0);
      grid_points[static_cast<size_t>(gy) * gw + gx] = cv::Point2d(g[0] / g[2] * n, g[1] / g[2] * n);
    }
  }
  int rows = 0;
  double sum = 0.0;
  for (int y = box.y; y < box.y + box.height; ++y) {
    for (int x = box.x; x < box.x + box.width; ++x) {
      const cv::Vec3d c = to_unit * cv::Vec3d(x, y, 1.0);
      const double cu = c[0] / c[2], cv_ = c[1] / c[2];
      if (cu < -margin || cv_ < -margin || cu > 1.0 + margin || cv_ > 1.0 + margin) continue;
      int touches = 1;
      const cv::Point2d* g = &grid_points[static_cast<size_t>(y - box.y) * gw + (x - box.x)];
      // The samples are convex combinations of the pixel's corners: when all four corners fall in
      // one cell, or on the outer side of one of the square's edges, so do all the samples, and the
      // pixel is that cell's (or the quiet zone's) whole (16 sixteenths add up to exactly 1).
      touched[0] = WholeCell(g[0], g[1], g[gw], g[gw + 1], n);
      if (touched[0] >= 0) {
        weight[0] = 1.0;
      } else {
        const cv::Point2d dx = g[1] - g[0], dy = g[gw] - g[0], dxy = g[gw + 1] - g[gw] - dx;
        touches = CoverageCounts(g[0], dx, dy, dxy, n, touched, counts);
        if (touches < 0) touches = CountSampleCells(g[0], dx, dy, dxy, n, touched, counts);
        for (int i = 0; i < touches; ++i) weight[i] = counts[i] * (1.0 / (kCoverageSamples * kCoverageSamples));
      }
      // Every weight a multiple of 1/16 and every product of two of 1/256: the sums below are exact
      // in any order (the same matrix whatever way a pixel's cells were counted).
      const double value = grey.at<uchar>(y, x);
      const int lowest = touched[0];
      for (int i = 0; i < touches; ++i) {
        const int a = touched[i];
        rhs[a] += weight[i] * value;
        double* row = lhs + static_cast<size_t>(a) * unknowns;
        if (lowest < first[a]) {
          std::fill(row + lowest, row + first[a], 0.0);
          first[a] = lowest;
        }
        for (int j = 0; j <= i; ++j) row[touched[j]] += weight[i] * weight[j];
      }
      sum += value;
      ++rows;
    }
  }
  if (rows < unknowns) return false;
  const double mean = sum / rows;
  const double ridge = kRidge * rows / unknowns;
  for (int a = 0; a < unknowns; ++a) {
    lhs[static_cast<size_t>(a) * unknowns + a] += ridge;
    rhs[a] += ridge * mean;
  }
  if (!SolveEnvelope(lhs, unknowns, first, rhs.data())) return false;
  cells.assign(rhs.begin(), rhs.begin() + n * n);
  quiet = rhs[n * n];
  return true;
}

// Whether a ring just outside the square (kQuietRingCells out, one sample per cell along each side)
// is on the quiet zone's side of `threshold`: white around a black marker, dark around an inverted
// one. A marker needs that margin to be found at all; a patch of texture that happens to read as a
// code usually has none.
bool QuietRing(const cv::Mat& grey, const cv::Matx33d& h, int n, double threshold, bool inverted) {
  const double out = kQuietRingCells / n;
  int samples = 0, quiet = 0;
  for (int k = 0; k < n; ++k) {
    const double t = (k + 0.5) / n;
    const double points[4][2] = {{t, -out}, {1.0 + out, t}, {t, 1.0 + out}, {-out, t}};
    for (const auto& uv : points) {
      double value = 0.0;
      if (!SampleUnit(grey, h, uv[0], uv[1], value)) continue;
      ++samples;
      quiet += (value > threshold) != inverted;
    }
  }
  return samples >= 3 * n && quiet >= kMinQuietShare * samples;
}

// The chance that a random pattern of `known` cells lies within `wrong` cells of some code of
// `dictionary` in some rotation.
double RandomMatchChance(const cv::aruco::Dictionary& dictionary, int known, int wrong) {
  double within = 0.0, ways = 1.0;  // patterns within e cells of one code, and C(known, e)
  for (int e = 0; e <= wrong; ++e) {
    within += ways;
    ways = ways * (known - e) / (e + 1);
  }
  return 4.0 * dictionary.bytesList.rows * within * std::ldexp(1.0, -known);
}

// Unknown cells a reading of `dictionary` may leave (kMaxChanceMatch).
int MaxUnknownCells(const cv::aruco::Dictionary& dictionary) {
  const int bits = dictionary.markerSize * dictionary.markerSize;
  int allowed = 0;
  while (allowed < kMaxUnknownCells && allowed + 1 < bits &&
         RandomMatchChance(dictionary, bits - allowed - 1, 0) <= kMaxChanceMatch) {
    ++allowed;
  }
  return allowed;
}

// Wrong cells a reading of `dictionary` with `known` cells known may have (kMaxChanceCorrected).
int MaxCorrectedCells(const cv::aruco::Dictionary& dictionary, int known) {
  int allowed = 0;
  while (allowed < kMaxCorrectedCells && allowed < known &&
         RandomMatchChance(dictionary, known, allowed + 1) <= kMaxChanceCorrected) {
    ++allowed;
  }
  return allowed;
}

// The one code and rotation of `dictionary` that agrees with `code` on the bits set in `known` but
// at most MaxCorrectedCells; false when none or several do. With every bit known and no correction
// allowed this is Dictionary::identify with no correction.
bool LookUp(const cv::aruco::Dictionary& dictionary, uint64_t code, uint64_t known, int& id, int& rotation) {
  const DictionaryCodes& codes = CodesOf(dictionary);
  const int allowed = MaxCorrectedCells(dictionary, PopCount(known));
  size_t match = 0;
  if (CountCodesAgreeing(codes, code, known, allowed, match) != 1) return false;
  id = static_cast<int>(match / 4);
  rotation = static_cast<int>(match % 4);
  return true;
}

// How far a reading of the cells got.
enum class Reading {
  kUnreadable,  // cells under a pixel, or too few pixels to estimate them
  kFlat,        // no contrast between the cells
  kMisframed,   // a dark square whose border or quiet zone reads wrong, too many cells unknown, or
                // a contrast just under kMinContrast: what a square a fraction of a cell off gives
  kNoCode,      // every cell clear, and no code of the dictionary matches them
  kRead,
};

// Reads the cells of the marker whose black square is h's unit square and looks them up. When read,
// `rotation` is Dictionary::identify's, which is how cv::aruco rotates its corners. `quiet_offset`,
// when given, receives the quiet zone's fitted level less the cells' threshold, in contrasts (set
// for every reading that is neither kUnreadable nor kFlat).
Reading ReadCells(const cv::Mat& grey, const cv::Matx33d& h, const cv::aruco::Dictionary& dictionary, int border_bits,
                  bool detect_inverted, int& id, int& rotation, double* quiet_offset = nullptr) {
  const int bits = dictionary.markerSize;
  const int n = bits + 2 * border_bits;
  if (bits * bits > 64) return Reading::kUnreadable;  // no predefined dictionary has more bits than a packed code
  // A cell under a pixel wide has no centre of its own to sample.
  if (ShortestSide(Corners(h)) < n) return Reading::kUnreadable;
  std::vector<double> cells;
  double quiet = 0.0;
  if (!EstimateCells(grey, h, n, cells, quiet)) return Reading::kUnreadable;
  // Otsu over the cells: the split of the sorted values with the largest between-class variance.
  std::vector<double> sorted(cells);
  std::sort(sorted.begin(), sorted.end());
  const int count = static_cast<int>(sorted.size());
  const double total = std::accumulate(sorted.begin(), sorted.end(), 0.0);
  double below = 0.0, best_variance = -1.0, dark = 0.0, bright = 0.0;
  int split = 0;
  for (int k = 1; k < count; ++k) {
    below += sorted[k - 1];
    const double m0 = below / k, m1 = (total - below) / (count - k);
    const double variance = double(k) * (count - k) * (m1 - m0) * (m1 - m0);
    if (variance > best_variance) {
      best_variance = variance;
      split = k;
      dark = m0;
      bright = m1;
    }
  }
  const double contrast = bright - dark;
  if (contrast < kMinMisframedContrast) return Reading::kFlat;
  const double threshold = 0.5 * (sorted[split - 1] + sorted[split]);
  if (quiet_offset) *quiet_offset = (quiet - threshold) / contrast;
  if (contrast < kMinContrast) return Reading::kMisframed;
  const auto unknown = [&](double cell) { return std::fabs(cell - threshold) < kMinCellMargin * contrast; };

  // Border cells: every known one black (white for an inverted marker); unknown ones count
  // against the budget below.
  int white_border = 0, black_border = 0, unknown_cells = 0;
  for (int y = 0; y < n; ++y) {
    for (int x = 0; x < n; ++x) {
      const bool inner = x >= border_bits && y >= border_bits && x < n - border_bits && y < n - border_bits;
      if (inner) continue;
      const double cell = cells[static_cast<size_t>(y) * n + x];
      if (unknown(cell)) ++unknown_cells;
      else if (cell > threshold) ++white_border;
      else ++black_border;
    }
  }
  const bool inverted = black_border == 0 && white_border > 0;
  if (white_border != 0 && !(inverted && detect_inverted)) return Reading::kMisframed;
  // The quiet zone: its fitted level clearly on the other side from the border, and a ring around
  // the square that stays there.
  if (inverted ? quiet > threshold - kQuietMargin * contrast : quiet < threshold + kQuietMargin * contrast) {
    return Reading::kMisframed;
  }
  if (!QuietRing(grey, h, n, threshold, inverted)) return Reading::kMisframed;
  unsigned char code[64], known[64];
  for (int y = 0; y < bits; ++y) {
    for (int x = 0; x < bits; ++x) {
      const double cell = cells[static_cast<size_t>(y + border_bits) * n + x + border_bits];
      known[y * bits + x] = !unknown(cell);
      unknown_cells += !known[y * bits + x];
      code[y * bits + x] = (cell > threshold) != inverted;
    }
  }
  if (unknown_cells > MaxUnknownCells(dictionary)) return Reading::kMisframed;
  return LookUp(dictionary, PackBits(code, bits * bits), PackBits(known, bits * bits), id, rotation) ? Reading::kRead
                                                                                                    : Reading::kNoCode;
}

// Where, along a profile of grey levels running from outside a quad inwards, the bright margin
// turns into the dark square: the sub-sample position of the first crossing, after the margin's
// brightest point, of the level halfway between it and the square. The profile may start dark
// (the contour runs along the dark pixels just outside the margin). -1 without such a crossing.
double EdgeFromOutside(const std::vector<double>& profile) {
  const int g = static_cast<int>(profile.size());
  const auto peak = std::max_element(profile.begin(), profile.begin() + g / 4);
  const double bright = *peak;
  const double dark = *std::min_element(peak, profile.begin() + g / 2);
  if (bright - dark < kMinContrast) return -1.0;
  const double mid = 0.5 * (bright + dark);
  for (int k = static_cast<int>(peak - profile.begin()); k + 1 < g / 2; ++k) {
    if (profile[k] >= mid && profile[k + 1] < mid) return k + (profile[k] - mid) / (profile[k] - profile[k + 1]);
  }
  return -1.0;
}

// The black square inside h's unit square, when that is the outline of a marker's quiet zone:
// each edge located from the mean grey profile across the middle of the quad. Inverted markers
// (white square, dark margin) with `inverted`.
bool InnerSquare(const cv::Mat& grey, const cv::Matx33d& h, int cells, bool inverted, cv::Matx33d& inner) {
  const int g = kProfileStepsPerCell * cells;
  const int band_from = g * 3 / 10, band_to = g * 7 / 10;
  std::vector<double> across(g, 0.0), down(g, 0.0);  // profiles along u and along v
  // No sample can leave the frame when the whole square maps inside it: no bounds checks then.
  const bool inside = UnitSquareInside(grey, h);
  for (int k = 0; k < g; ++k) {
    const double t = (k + 0.5) / g;
    for (int b = band_from; b < band_to; ++b) {
      const double s = (b + 0.5) / g;
      double a = 0.0, d = 0.0;
      if (!SampleUnit(grey, h, t, s, a, inside) || !SampleUnit(grey, h, s, t, d, inside)) return false;
      across[k] += inverted ? -a : a;
      down[k] += inverted ? -d : d;
    }
    across[k] /= band_to - band_from;
    down[k] /= band_to - band_from;
  }
  // Unit-square coordinate of a crossing found `steps` samples in from the start of a profile.
  const auto unit = [g](double steps) { return (steps + 0.5) / g; };
  const std::vector<double> across_back(across.rbegin(), across.rend()), down_back(down.rbegin(), down.rend());
  const double left = EdgeFromOutside(across), right = EdgeFromOutside(across_back);
  const double top = EdgeFromOutside(down), bottom = EdgeFromOutside(down_back);
  if (left < 0.0 || right < 0.0 || top < 0.0 || bottom < 0.0) return false;
  const double u0 = unit(left), u1 = 1.0 - unit(right), v0 = unit(top), v1 = 1.0 - unit(bottom);
  // A marker fills most of its quiet-zone outline; the margins are a cell or two.
  if (u1 - u0 < 0.4 || v1 - v0 < 0.4) return false;
  inner = SubSquare(h, u0, v0, u1, v1);
  return true;
}

// The marker read as `id` in `rotation` on the black square `square`, when its whole pattern
// explains the pixels.
bool Accept(const cv::Mat& grey, const cv::aruco::Dictionary& dictionary, int border_bits, const cv::Matx33d& square,
            int id, int rotation, SmallMarker& marker) {
  std::array<cv::Point2f, 4> corners = Corners(square);
  std::rotate(corners.begin(), corners.begin() + 4 - rotation, corners.end());
  if (!PatternExplainsPixels(grey, dictionary, id, border_bits, corners, &marker.fit)) return false;
  marker.id = id;
  marker.corners = corners;
  return true;
}

}  // namespace

bool DecodeSmall(const cv::Mat& grey, const std::array<cv::Point2f, 4>& candidate,
                 const cv::aruco::Dictionary& dictionary, int border_bits, bool detect_inverted, SmallMarker& marker) {
  if (grey.type() != CV_8UC1 || grey.cols < 2 || grey.rows < 2) return false;
  const int cells = dictionary.markerSize + 2 * border_bits;
  if (!SmallCandidateSide(MeanSide(candidate), cells)) return false;
  std::array<cv::Point2f, 4> quad = candidate;
  // Clockwise in the image (y down), as cv::aruco orders candidates: the cells are then read in the
  // marker's own orientation, not mirrored.
  const cv::Point2f d1 = quad[1] - quad[0], d2 = quad[2] - quad[0];
  const double turn = double(d1.x) * d2.y - double(d1.y) * d2.x;
  if (!(std::fabs(turn) > 0.0)) return false;
  if (turn < 0.0) std::swap(quad[1], quad[3]);
  const cv::Matx33d h = SquareToQuad(quad);

  // The quad grown by fractions of a pixel; as a black square whose contour is a pixel off on some
  // sides, each side moved onto its grey-level edge; as a quiet-zone outline; as one pushed out into
  // its quiet zone and located again from the grey levels. Each framing is only made when those
  // before it failed to read: the first that reads is the same, and on bench's dim distant set 32 of
  // the 44 misframed candidates read on a growth, before the edge fit and the quiet-zone profiles
  // would have been made. The quad itself is not read: a blurred square's contour lies inside its
  // edges (kGrowPx). Read first, 1 of its 133 readings read a marker; read after the growths, 3 over
  // bench's 19 sets and the real photos (kMaxMisframedQuiet's run), and without it the same markers
  // are found, their corners within 0.05 px, for 12 % fewer cell estimates. The first growth's
  // reading is the gate for the others.
  int id = -1, rotation = 0;
  double quiet_offset = 0.0;
  // The quad with each side moved out by `px`.
  const auto grown = [&h, side = MeanSide(quad)](double px) {
    const double g = px / side;
    return SubSquare(h, -g, -g, 1.0 + g, 1.0 + g);
  };
  const bool fine = MeanSide(quad) < kFineGrowMaxPxPerCell * cells;
  const double* grow = fine ? kFineGrowPx : kGrowPx;
  const size_t grows = fine ? std::size(kFineGrowPx) : std::size(kGrowPx);
  const cv::Matx33d first = grown(grow[0]);
  const Reading gate = ReadCells(grey, first, dictionary, border_bits, detect_inverted, id, rotation, &quiet_offset);
  if (gate == Reading::kRead && Accept(grey, dictionary, border_bits, first, id, rotation, marker)) return true;
  // The others only when the square framed a marker-like square wrongly, with a marker's
  // surroundings (kMaxMisframedQuiet): misframed; read as a code the pattern fit then refused; or,
  // under kFineGrowMaxPxPerCell, every cell clear but no code (a 0.3 px growth can carry a cell
  // across the threshold: two 14-15 px markers of bench's distant set, misframed as the plain contour).
  // Most clutter reads flat, unreadable or as a clear code of no marker, and costs nothing more.
  const bool misframed = gate == Reading::kMisframed || gate == Reading::kRead || (fine && gate == Reading::kNoCode);
  if (!misframed || std::fabs(quiet_offset) > kMaxMisframedQuiet) return false;
  const auto read = [&](const cv::Matx33d& square) {
    return ReadCells(grey, square, dictionary, border_bits, detect_inverted, id, rotation) == Reading::kRead &&
           Accept(grey, dictionary, border_bits, square, id, rotation, marker);
  };
  for (size_t k = 1; k < grows; ++k) {
    if (read(grown(grow[k]))) return true;
  }
  // Each side moved onto its own grey-level edge: a contour can be off by more on one side than a
  // uniform growth corrects (blur, tilt, a pixel of noise on the threshold).
  std::array<cv::Point2f, 4> edges = quad;
  if (RefineCornersOnEdges(grey, edges, cells) > 0 && read(SquareToQuad(edges))) return true;
  cv::Matx33d inner;
  const double e = kExpandCells / cells;
  const cv::Matx33d expanded = SubSquare(h, -e, -e, 1.0 + e, 1.0 + e);
  for (const bool inverted : {false, true}) {
    if (inverted && !detect_inverted) break;
    if (InnerSquare(grey, h, cells, inverted, inner) && read(inner)) return true;
    if (InnerSquare(grey, expanded, cells, inverted, inner) && read(inner)) return true;
  }
  // Last, under kFineGrowMaxPxPerCell: one side of the contour can lie most of a cell further in
  // than the others, and the edge fit from there takes the inner edge of the border cells for the
  // square's; from the contour grown by kEdgeStartGrowPx it reaches the outer one.
  if (!fine) return false;
  std::array<cv::Point2f, 4> start = Corners(grown(kEdgeStartGrowPx));
  return RefineCornersOnEdges(grey, start, cells) > 0 && read(SquareToQuad(start));
}

size_t SmallCellEstimates() { return cell_estimates; }

bool PatternExplainsPixels(const cv::Mat& grey, const cv::aruco::Dictionary& dictionary, int id, int border_bits,
                           const std::array<cv::Point2f, 4>& corners, FittedPattern* fit) {
  // RefineCornersOnPattern's fit, keeping the blur it finds.
  FittedPattern fitted;
  fitted.corners = corners;
  if (!RefineCornersOnPatternFrom(grey, MarkerCells(dictionary, id, border_bits), fitted.corners, fitted.blur,
                                  kColdLastStep)) {
    return false;
  }
  if (fit) *fit = fitted;
  return true;
}

namespace {

// cv::aruco's "too close" test (_filterTooCloseCandidates): corners, in some cyclic order, closer
// RMS than `rate` of the smaller perimeter.
bool TooClose(const std::array<cv::Point2f, 4>& a, const std::array<cv::Point2f, 4>& b, double rate) {
  return CornersWithin(a, b, rate * 4.0 * std::min(MeanSide(a), MeanSide(b)));
}

std::array<cv::Point2f, 4> ToArray(const std::vector<cv::Point2f>& v) {
  std::array<cv::Point2f, 4> a{};
  std::copy_n(v.begin(), std::min<size_t>(4, v.size()), a.begin());
  return a;
}

}  // namespace

std::vector<size_t> SmallCandidates(const std::vector<std::vector<cv::Point2f>>& rejected, int cells) {
  std::vector<size_t> small;
  std::vector<float> side(rejected.size(), 0.0f);
  for (size_t i = 0; i < rejected.size(); ++i) {
    if (rejected[i].size() != 4) continue;
    side[i] = MeanSide(ToArray(rejected[i]));
    if (SmallCandidateSide(side[i], cells)) small.push_back(i);
  }
  if (small.size() > kMaxSmallCandidates) {
    // The biggest (the most pixels per cell, the likeliest to read), then back in cv::aruco's order.
    std::nth_element(small.begin(), small.begin() + kMaxSmallCandidates, small.end(),
                     [&side](size_t a, size_t b) { return side[a] > side[b] || (side[a] == side[b] && a < b); });
    small.resize(kMaxSmallCandidates);
    std::sort(small.begin(), small.end());
  }
  return small;
}

std::vector<SmallMarker> DecodeRejected(const cv::Mat& grey, const std::vector<std::vector<cv::Point2f>>& rejected,
                                        const std::vector<std::vector<cv::Point2f>>& found_corners,
                                        const std::vector<int>& found_ids, const cv::aruco::Dictionary& dictionary,
                                        const cv::aruco::DetectorParameters& parameters) {
  std::vector<SmallMarker> markers;
  for (const size_t index : SmallCandidates(rejected, dictionary.markerSize + 2 * parameters.markerBorderBits)) {
    const auto& candidate = rejected[index];
    SmallMarker marker;
    if (!DecodeSmall(grey, ToArray(candidate), dictionary, parameters.markerBorderBits,
                     parameters.detectInvertedMarker, marker)) {
      continue;
    }
    bool duplicate = false;
    for (size_t i = 0; i < found_ids.size() && !duplicate; ++i) {
      duplicate = found_ids[i] == marker.id &&
                  TooClose(ToArray(found_corners[i]), marker.corners, parameters.minMarkerDistanceRate);
    }
    for (const auto& m : markers) {
      duplicate = duplicate || (m.id == marker.id && TooClose(m.corners, marker.corners, parameters.minMarkerDistanceRate));
    }
    if (duplicate) continue;
    if (parameters.cornerRefinementMethod == cv::aruco::CORNER_REFINE_SUBPIX) {
      std::vector<cv::Point2f> corners(marker.corners.begin(), marker.corners.end());
      cv::cornerSubPix(grey, corners, cv::Size(parameters.cornerRefinementWinSize, parameters.cornerRefinementWinSize),
                       cv::Size(-1, -1),
                       cv::TermCriteria(cv::TermCriteria::MAX_ITER | cv::TermCriteria::EPS,
                                        parameters.cornerRefinementMaxIterations,
                                        parameters.cornerRefinementMinAccuracy));
      std::copy(corners.begin(), corners.end(), marker.corners.begin());
    }
    markers.push_back(marker);
  }
  return markers;
}

// The cell coordinates of row j of a pixel's samples (CoverageSampleCells), one rounding per product
// and sum: CoverageSampleCells and CoverageCounts place every sample alike.
ARUCOTAG_INLINE ARUCOTAG_NO_FUSED_MULTIPLY_ADD void SampleRow(const cv::Point2d& p00, const cv::Point2d& dx,
                                                              const cv::Point2d& dy, const cv::Point2d& dxy, int j,
                                                              Double4& x, Double4& y) {
  const Double4 along = {0.125, 0.375, 0.625, 0.875};  // (i + 0.5) / 4, exact
  const double fy = (j + 0.5) / kCoverageSamples;
  const double down_x = dy.x * fy, down_y = dy.y * fy, bend_x = dxy.x * fy, bend_y = dxy.y * fy;
  const double row_x = p00.x + down_x, row_y = p00.y + down_y;
  const double step_x = dx.x + bend_x, step_y = dx.y + bend_y;
  const Double4 offset_x = step_x * along, offset_y = step_y * along;
  x = row_x + offset_x;
  y = row_y + offset_y;
}

ARUCOTAG_VECTOR_CLONES ARUCOTAG_NO_FUSED_MULTIPLY_ADD void CoverageSampleCells(const cv::Point2d& p00,
                                                                              const cv::Point2d& dx,
                                                                              const cv::Point2d& dy,
                                                                              const cv::Point2d& dxy, int n,
                                                                              int* cells) {
  static_assert(kCoverageSamples == 4, "a row of samples is one vector");
  const double side = n;
  for (int j = 0; j < kCoverageSamples; ++j) {
    Double4 x, y;
    SampleRow(p00, dx, dy, dxy, j, x, y);
    // floor(x) in [0, n) exactly when x is, and there floor is truncation; NaN is outside.
    const auto inside = (x >= 0.0) & (x < side) & (y >= 0.0) & (y < side);
    const Double4 cx = __builtin_convertvector(__builtin_convertvector(inside ? x : 0.0, Int4), Double4);
    const Double4 cy = __builtin_convertvector(__builtin_convertvector(inside ? y : 0.0, Int4), Double4);
    const Double4 row_start = cy * side;
    const Int4 cell = __builtin_convertvector(inside ? row_start + cx : side * side, Int4);
    std::memcpy(cells + j * kCoverageSamples, &cell, sizeof cell);
  }
}

ARUCOTAG_VECTOR_CLONES ARUCOTAG_NO_FUSED_MULTIPLY_ADD int CoverageCounts(const cv::Point2d& p00, const cv::Point2d& dx,
                                                                         const cv::Point2d& dy, const cv::Point2d& dxy,
                                                                         int n, int* cells, int* counts) {
  static_assert(kCoverageSamples == 4, "a row of samples is one vector");
  // The pixel's corners bound its samples (convex combinations of them, to a rounding of 1e-14 at
  // most at these coordinates). Cells from (cx0, cy0): with the corners kMargin clear of the cell
  // lines that bound three columns and rows of them, each sample's column is cx0 plus the count of
  // the two lines between it passes, exactly the floor CoverageSampleCells takes.
  constexpr double kMargin = 1e-9;
  const cv::Point2d p10 = p00 + dx, p01 = p00 + dy, p11 = p01 + dx + dxy;
  const double lo_x = std::min({p00.x, p10.x, p01.x, p11.x}), hi_x = std::max({p00.x, p10.x, p01.x, p11.x});
  const double lo_y = std::min({p00.y, p10.y, p01.y, p11.y}), hi_y = std::max({p00.y, p10.y, p01.y, p11.y});
  // In [0, n - 1] (std::max keeps 0 for a NaN, which the tests below then refuse).
  const int cx0 = FloorInt(std::min(std::max(0.0, lo_x), n - 1.0)), cy0 = FloorInt(std::min(std::max(0.0, lo_y), n - 1.0));
  const bool fits_x = hi_x <= cx0 + 3 - kMargin && (lo_x < 0.0 || lo_x >= cx0 + kMargin);
  const bool fits_y = hi_y <= cy0 + 3 - kMargin && (lo_y < 0.0 || lo_y >= cy0 + kMargin);
  if (!(fits_x && fits_y)) return -1;
  // Each sample adds one to a 6-bit count (16 at most) of its slot: row * 3 + column of the 3 x 3
  // cells from (cx0, cy0), or kOutside outside the square. Ten counts fill 60 bits.
  typedef int64_t Long4 __attribute__((vector_size(4 * sizeof(int64_t))));
  constexpr int kSlotBits = 6, kOutside = 9;
  const double side = n, x1 = cx0 + 1, x2 = cx0 + 2, y1 = cy0 + 1, y2 = cy0 + 2;
  const Long4 one = {1, 1, 1, 1}, outside = one * (kOutside * kSlotBits);
  Long4 sums = {0, 0, 0, 0};
  for (int j = 0; j < kCoverageSamples; ++j) {
    Double4 x, y;
    SampleRow(p00, dx, dy, dxy, j, x, y);
    const Long4 inside = (x >= 0.0) & (x < side) & (y >= 0.0) & (y < side);
    // Comparisons give -1 where true: minus the lines passed, times the slot's bits.
    const Long4 column = (x >= x1) + (x >= x2), row = (y >= y1) + (y >= y2);
    const Long4 shift = inside ? -(row * 3 + column) * kSlotBits : outside;
    sums += one << shift;
  }
  uint64_t total = static_cast<uint64_t>(sums[0] + sums[1] + sums[2] + sums[3]);
  // The slots with a count (bit 0 of each field set where any of its five low bits is), in order:
  // the cells ascending (n > 2), the outside (n * n) last.
  constexpr uint64_t kFieldBits = 0x041041041041041ull;  // bit 0 of each of the ten fields
  uint64_t used = (total | total >> 1 | total >> 2 | total >> 3 | total >> 4) & kFieldBits;
  static constexpr int kRow[] = {0, 0, 0, 1, 1, 1, 2, 2, 2}, kColumn[] = {0, 1, 2, 0, 1, 2, 0, 1, 2};
  int found = 0;
  for (; used != 0; used &= used - 1) {
    const int bit = __builtin_ctzll(used), k = bit / kSlotBits;
    cells[found] = k == kOutside ? n * n : (cy0 + kRow[k]) * n + cx0 + kColumn[k];
    counts[found++] = static_cast<int>((total >> bit) & ((1u << kSlotBits) - 1));
  }
  return found;
}

bool SolveEnvelope(cv::Mat& normal, cv::Mat& rhs) {
  CV_Assert(normal.type() == CV_64F && rhs.type() == CV_64F && normal.rows == normal.cols && rhs.rows == normal.rows &&
            rhs.cols == 1 && normal.isContinuous() && rhs.isContinuous());
  const int m = normal.rows;
  const double* a = normal.ptr<double>();
  // Row i of the lower triangle is zero left of first[i].
  std::vector<int> first(static_cast<size_t>(m));
  for (int i = 0; i < m; ++i) {
    int f = 0;
    while (f < i && a[static_cast<size_t>(i) * m + f] == 0.0) ++f;
    first[i] = f;
  }
  return SolveEnvelope(normal.ptr<double>(), m, first.data(), rhs.ptr<double>());
}

bool SolveEnvelope(double* a, int m, const int* first, double* b) {
  const auto at = [a, m](int i, int j) -> double& { return a[static_cast<size_t>(i) * m + j]; };
  // Row i of L is zero left of first[i] too: its entries there are sums of nothing.
  // L L^T = normal, L over the lower triangle, its diagonal stored inverted; the products are
  // summed in the order of the dense factorisation, less the ones with a zero factor.
  for (int i = 0; i < m; ++i) {
    for (int j = first[i]; j < i; ++j) {
      double s = at(i, j);
      for (int k = std::max(first[i], first[j]); k < j; ++k) s -= at(i, k) * at(j, k);
      at(i, j) = s * at(j, j);
    }
    double s = at(i, i);
    for (int k = first[i]; k < i; ++k) s -= at(i, k) * at(i, k);
    if (s < std::numeric_limits<double>::epsilon()) return false;
    at(i, i) = 1.0 / std::sqrt(s);
  }
  // L y = b, then L^T x = y, in place.
  for (int i = 0; i < m; ++i) {
    double s = b[i];
    for (int k = first[i]; k < i; ++k) s -= at(i, k) * b[k];
    b[i] = s * at(i, i);
  }
  // Row by row from the last: once x[i] is known it comes off every b[k] its row of L reaches, so each
  // b[k] loses its terms in the order of descending i, the order a dot product over column k of L
  // would take them (the same values to the bit), without visiting the zeros left of each row's
  // envelope (a test per entry of the whole triangle was 30 % of this solve).
  for (int i = m - 1; i >= 0; --i) {
    b[i] *= at(i, i);
    const double x = b[i];
    for (int k = first[i]; k < i; ++k) b[k] -= at(i, k) * x;
  }
  return true;
}

}  // namespace arucotag::internal

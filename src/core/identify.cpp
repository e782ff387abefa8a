// Identification of the fast path's candidates. Each candidate is decoded on the full-resolution
// frame the way cv::aruco decodes it (perspective removal, Otsu, border bits, dictionary look-up);
// small ones that reading rejects get cv::aruco's contours and then the second-chance decoder
// (decode_small.cpp). For the edge-fit refinement, which keeps its start where it cannot measure an
// edge, each marker's starting corners are then re-derived as cv::aruco's own (its three windows, on
// a small window around the marker), so the result is the full search's; for cv::aruco's sub-pixel
// refinement any nearby start converges to the same corner (RefineCorner).
#include "identify.hpp"

#include "codes.hpp"
#include "decode_small.hpp"
#include "parallel.hpp"
#include "refine_corner.hpp"
#include "refine_edges.hpp"

#include <algorithm>
#include <cfloat>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <mutex>
#include <numeric>
#include <tuple>
#include <utility>

#include <opencv2/imgproc.hpp>

namespace arucotag::internal {

const DictionaryCodes& CodesOf(const cv::aruco::Dictionary& dictionary) {
  thread_local DictionaryCodes cache;
  const cv::Mat& list = dictionary.bytesList;
  const int nbytes = (dictionary.markerSize * dictionary.markerSize + 7) / 8;
  // Every (rows / 16)th marker's bytes compared with those the cache was made from: at most 16 runs of
  // 4 nbytes bytes, a few memcmp calls. A checksum of them, a multiply-add a byte in one dependency
  // chain, ran on every look-up (callgrind of Detect on 640x480 frames of 50 markers: 100.71 -> 100.43 M).
  const int stride = std::max(1, list.rows / 16);
  const size_t run = static_cast<size_t>(4 * nbytes);
  const auto same_samples = [&] {
    if (cache.data != list.data || cache.rows != list.rows || cache.cols != list.cols) return false;
    const uchar* kept = cache.sampled.data();
    for (int m = 0; m < list.rows; m += stride, kept += run) {
      if (std::memcmp(kept, list.ptr(m), run) != 0) return false;
    }
    return true;
  };
  if (same_samples()) return cache;
  cache = DictionaryCodes();
  cache.data = list.data;
  cache.rows = list.rows;
  cache.cols = list.cols;
  for (int m = 0; m < list.rows; m += stride) {
    cache.sampled.insert(cache.sampled.end(), list.ptr(m), list.ptr(m) + run);
  }
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

// The scans of every code: a tag36h11 look-up takes 2348 popcounts, which the AVX2 clones make one
// instruction each (callgrind of Detect: the distant tag36h11 set 138.7 -> 134.2 M, the dim one
// 122.1 -> 118.2 M, the photos 60.4 -> 59.0 M, the warped photos (DICT_5X5_1000, 4000 codes to scan)
// 133.3 -> 113.1 M with the pattern fit's change before it; the same markers and corners).
ARUCOTAG_VECTOR_CLONES int FirstCodeWithin(const DictionaryCodes& codes, uint64_t candidate, int max_distance,
                                           int& rotation) {
  const uint64_t* code = codes.code.data();
  const int markers = static_cast<int>(codes.code.size() / 4);
  for (int m = 0; m < markers; ++m, code += 4) {
    int best = max_distance + 1;
    for (int r = 0; r < 4; ++r) {
      const int distance = PopCount(code[r] ^ candidate);
      if (distance < best) {
        best = distance;
        rotation = r;
      }
    }
    if (best <= max_distance) return m;
  }
  return -1;
}

ARUCOTAG_VECTOR_CLONES int CountCodesAgreeing(const DictionaryCodes& codes, uint64_t code, uint64_t known,
                                              int allowed, size_t& match) {
  int matches = 0;
  for (size_t k = 0; k < codes.code.size() && matches < 2; ++k) {
    if (PopCount((codes.code[k] ^ code) & known) > allowed) continue;
    ++matches;
    match = k;
  }
  return matches;
}

uint64_t PackBits(const unsigned char* bits, int count) {
  uint64_t packed = 0;
  for (int k = 0; k < count;) {
    unsigned byte = 0;
    for (const int end = std::min(count, k + 8); k < end; ++k) byte = (byte << 1) | (bits[k] ? 1u : 0u);
    packed = (packed << 8) | byte;  // a last partial byte keeps its bits at its low end
  }
  return packed;
}

// Where the pixels of one canonical row come from: the offset of the source pixel in the frame, or
// -1 outside it (warpPerspective's constant border). (x0 + dx x, y0 + dy x) / (w0 + dw x) rounded to
// the nearest pixel in warpPerspective's INTER_NEAREST arithmetic (double, no fused multiply-add,
// 1 / 0 taken as 0, cvRound's ties to even), four pixels at a time: adding and subtracting
// 1.5 * 2^52 rounds a double under 2^51 to the nearest integer, ties to even, as cvRound's
// conversion does, and anything larger is far outside the frame either way. Each product is its
// own statement (ARUCOTAG_NO_FUSED_MULTIPLY_ADD).
// `offsets` holds size rounded up to whole vectors of four.
ARUCOTAG_VECTOR_CLONES ARUCOTAG_NO_FUSED_MULTIPLY_ADD void CanonicalRowSources(double x0, double y0, double w0,
                                                                              double dx, double dy, double dw, int size,
                                                                              int cols, int rows, int step,
                                                                              int* offsets) {
  constexpr double kRound = 6755399441055744.0;
  const double last_x = cols - 1, last_y = rows - 1, row = step;
  for (int x = 0; x < size; x += 4) {
    const Double4 at = x + Double4{0.0, 1.0, 2.0, 3.0};
    const Double4 dw_at = dw * at, dx_at = dx * at, dy_at = dy * at;
    const Double4 w = w0 + dw_at;
    const Double4 inverse = 1.0 / (w != 0.0 ? w : HUGE_VAL);
    const Double4 fx = (x0 + dx_at) * inverse, fy = (y0 + dy_at) * inverse;
    const Double4 sx = (fx + kRound) - kRound, sy = (fy + kRound) - kRound;
    const auto inside = (sx >= 0.0) & (sx <= last_x) & (sy >= 0.0) & (sy <= last_y);
    const Int4 offset = __builtin_convertvector(inside ? sy * row + sx : -1.0, Int4);
    std::memcpy(offsets + x, &offset, sizeof offset);
  }
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
  if (size > kMaxUnwarpedSide) return false;  // a configuration Detector refuses
  // Canonical pixel (x, y) is (u, v) = (x, y) / (size - 1) of the unit square.
  const cv::Matx33d h = SquareToQuad(corners) * cv::Matx33d(1.0 / (size - 1), 0, 0, 0, 1.0 / (size - 1), 0, 0, 0, 1);
  thread_local std::vector<uchar> canonical_buffer;
  canonical_buffer.resize(static_cast<size_t>(size) * size);
  // Through a plain pointer: each use of a thread_local in a shared library is a call to
  // __tls_get_addr, which the compiler repeated row by row.
  uchar* const canonical = canonical_buffer.data();
  const uchar* pixels = grey.data;
  // The histogram for Otsu's threshold is counted as the pixels are read, into four histograms by
  // column: neighbouring pixels often share a level, and one histogram made each count wait for the
  // last one's store (perf: a third of Identify's time on this loop).
  int histograms[4][256] = {};
  int offsets[kMaxUnwarpedSide + 3];  // whole vectors of four
  for (int y = 0; y < size; ++y) {
    CanonicalRowSources(h(0, 1) * y + h(0, 2), h(1, 1) * y + h(1, 2), h(2, 1) * y + h(2, 2), h(0, 0), h(1, 0), h(2, 0),
                        size, grey.cols, grey.rows, static_cast<int>(grey.step), offsets);
    uchar* out = &canonical[static_cast<size_t>(y) * size];
    for (int x = 0; x < size; ++x) {
      out[x] = offsets[x] >= 0 ? pixels[offsets[x]] : 0;
      ++histograms[x & 3][out[x]];
    }
  }
  int histogram[256];
  for (int i = 0; i < 256; ++i) histogram[i] = histograms[0][i] + histograms[1][i] + histograms[2][i] + histograms[3][i];

  uchar bits[kMaxCells][kMaxCells] = {};
  // Spread of the inner part (half a cell trimmed): too flat means all one colour, no Otsu. Summed
  // in integers, the same exact values as in double; a row's squares stay within int up to 33k px.
  int64_t sum = 0, sum_sq = 0;
  for (int y = cell / 2; y < size - cell / 2; ++y) {
    const uchar* row = &canonical[static_cast<size_t>(y) * size];
    int row_sum = 0, row_sq = 0;
    for (int x = cell / 2; x < size - cell / 2; ++x) {
      row_sum += row[x];
      row_sq += row[x] * row[x];
    }
    sum += row_sum;
    sum_sq += row_sq;
  }
  const double n_inner = double(size - 2 * (cell / 2)) * (size - 2 * (cell / 2));
  const double mean = sum / n_inner;
  const double stddev = std::sqrt(std::max(0.0, sum_sq / n_inner - mean * mean));
  if (stddev < p.minOtsuStdDev) {
    for (auto& row : bits) std::fill(std::begin(row), std::end(row), mean > 127 ? 1 : 0);
  } else {
    // OpenCV's getThreshVal_Otsu_8u, over the grey levels that occur: at an empty level q1 and mu1
    // keep their values (up to round-off), so its sigma only repeats the last level's, and a
    // threshold moved onto an empty level splits the pixels as the level before it does.
    const double scale = 1.0 / canonical_buffer.size();
    // The levels' sum in integers (a loop that vectorises): the same exact value as OpenCV's sum of
    // i * histogram[i] in double, every partial sum an integer under 2^53.
    int64_t level_sum = 0;
    for (int i = 0; i < 256; ++i) level_sum += i * histogram[i];
    const double mu = static_cast<double>(level_sum) * scale;
    // The levels that occur listed first, without a branch (a store at every level, the count moved
    // where it occurs): a test per level of which are empty mispredicted about one level in ten
    // (callgrind's branch simulation, 640x480/50: 26 k of Identify's 43 k mispredictions).
    int levels[256];
    int occurring = 0;
    for (int i = 0; i < 256; ++i) {
      levels[occurring] = i;
      occurring += histogram[i] != 0;
    }
    double mu1 = 0.0, q1 = 0.0, max_sigma = 0.0;
    int threshold = 0;
    for (int k = 0; k < occurring; ++k) {
      const int i = levels[k];
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
    // Each cell's white pixels: per row of cells, the white pixels of each canonical column over the
    // cells' inner rows (whole rows at a time, which vectorise), then each cell's inner columns.
    const int inner = cell - 2 * margin;
    int white_in_column[kMaxUnwarpedSide];
    for (int y = 0; y < with_borders; ++y) {
      std::fill_n(white_in_column, size, 0);
      for (int v = 0; v < inner; ++v) {
        const uchar* px = &canonical[static_cast<size_t>(y * cell + margin + v) * size];
        for (int x = 0; x < size; ++x) white_in_column[x] += px[x] > threshold;
      }
      for (int x = 0; x < with_borders; ++x) {
        int white = 0;
        for (int u = 0; u < inner; ++u) white += white_in_column[x * cell + margin + u];
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
  unsigned char inner[kMaxCells * kMaxCells];
  for (int y = 0; y < marker_size; ++y) {
    for (int x = 0; x < marker_size; ++x) inner[y * marker_size + x] = bits[y + b][x + b];
  }
  const int max_correction = static_cast<int>(double(dictionary.maxCorrectionBits) * p.errorCorrectionRate);
  const DictionaryCodes& codes = CodesOf(dictionary);
  const uint64_t candidate = PackBits(inner, marker_size * marker_size);
  int nearest = -1;
  const int m = FirstCodeWithin(codes, candidate, max_correction, nearest);
  if (m < 0) return false;
  id = m;
  rotation = nearest;
  return true;
}

namespace {

// px: markers whose mean side is under this keep their own edge fit, settled or not (see Decode).
constexpr float kSettleMinSide = 20.0f;

// Whether point `p` lies strictly inside the quad (cv::pointPolygonTest > 0), its bounding box
// tested first.
bool StrictlyInside(const std::array<cv::Point2f, 4>& quad, const cv::Point2f& p) {
  float x0 = quad[0].x, x1 = x0, y0 = quad[0].y, y1 = y0;
  for (const auto& c : quad) {
    x0 = std::min(x0, c.x);
    x1 = std::max(x1, c.x);
    y0 = std::min(y0, c.y);
    y1 = std::max(y1, c.y);
  }
  if (!(p.x > x0 && p.x < x1 && p.y > y0 && p.y < y1)) return false;
  const cv::Mat outline(4, 1, CV_32FC2, const_cast<cv::Point2f*>(quad.data()));
  return cv::pointPolygonTest(outline, p, false) > 0.0;
}

// Whether quad `q` lies on the marker read as `marker`: its centre inside the marker when the marker
// is bigger (one of its cells), the marker's centre inside `q` otherwise (the outline of its quiet
// zone, or the marker itself at another level).
bool OnMarker(const Quad& q, const Quad& marker) {
  return marker.area > q.area ? StrictlyInside(marker.corners, Centre(q.corners))
                              : StrictlyInside(q.corners, Centre(marker.corners));
}

// The second-chance decoder's results on one frame, by the contour it was given: neighbouring quads
// of one square (found at two levels, or by two windows) trace the same contours of cv::aruco's around
// it, and DecodeSmall reads an exact repeat as it did the first time. On the real 640x480 photos 5 of
// 25 second looks were repeats (the ChArUco board's squares), each one to nine readings of the cells.
// Shared by the threads that decode small quads.
class SecondLooks {
 public:
  // DecodeSmall of `corners`, computed once.
  bool Decode(const cv::Mat& grey, const std::array<cv::Point2f, 4>& corners, const cv::aruco::Dictionary& dictionary,
              int border_bits, bool detect_inverted, SmallMarker& marker) {
    {
      const std::lock_guard<std::mutex> lock(mutex_);
      for (const Look& look : looks_) {
        if (look.corners != corners) continue;
        marker = look.marker;
        return look.read;
      }
    }
    const bool read = DecodeSmall(grey, corners, dictionary, border_bits, detect_inverted, marker);
    const std::lock_guard<std::mutex> lock(mutex_);
    looks_.push_back({corners, read, marker});
    return read;
  }

 private:
  struct Look {
    std::array<cv::Point2f, 4> corners;
    bool read;
    SmallMarker marker;
  };
  std::mutex mutex_;
  std::vector<Look> looks_;
};

// Decodes a small quad cv::aruco's reading rejected (`decoded` and `id` set on success). At this
// size a one-pixel difference of the contour flips cells of its 4-px-per-cell reading, and
// cv::aruco's windows (3, 13, 23 px) trace slightly different contours than this search's: those
// are traced on the quad's neighbourhood and read the same way first, so that every marker the full
// search decodes is decoded here too. What still fails gets the second-chance decoder, on this
// contour and on cv::aruco's (`second_chance` set: cv::aruco has no corners of its own there), when
// `second_look` asks for it. Either way a pattern fit checks the reading; `checked` receives it.
bool DecodeSmallQuad(const Pyramid& pyramid, const DetectorConfig& config, const cv::aruco::Dictionary& dictionary,
                     const cv::aruco::DetectorParameters& p, const Quad& quad, bool second_look, Quad& decoded, int& id,
                     bool& second_chance, FittedPattern& checked, SecondLooks& looks) {
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
    if (!PatternExplainsPixels(grey, dictionary, id, p.markerBorderBits, decoded.corners, &checked)) continue;
    return true;
  }
  if (!second_look) return false;
  local.insert(local.begin(), quad);
  for (auto q = local.begin(); q != local.end(); ++q) {
    // A contour one of cv::aruco's windows traces exactly as this search did reads as it did
    // (the photos' ChArUco board: 3 of 44 second looks, each a few million instructions).
    if (std::any_of(local.begin(), q, [&](const Quad& tried) { return tried.corners == q->corners; })) continue;
    SmallMarker marker;
    if (!looks.Decode(grey, q->corners, dictionary, p.markerBorderBits, p.detectInvertedMarker, marker)) continue;
    decoded = *q;
    decoded.corners = marker.corners;
    id = marker.id;
    second_chance = true;
    checked = marker.fit;
    return true;
  }
  return false;
}

}  // namespace

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
  const size_t n = quads.size();
  std::vector<int> ids(n, -1);
  std::vector<Quad> decoded(quads);
  std::vector<char> second_chance(n, 0);
  std::vector<FittedPattern> checked(n);
  std::vector<size_t> read;  // quads read so far
  // Each quad's bounding box (a decoded quad's corners are its quad's, rotated): OnMarker holds only
  // where two boxes meet, so the quads are tested against the markers read only there. A pixel of
  // margin covers the rounding of a centre.
  std::vector<cv::Vec4f> box(n);
  for (size_t i = 0; i < n; ++i) {
    const auto& c = quads[i].corners;
    box[i] = {std::min({c[0].x, c[1].x, c[2].x, c[3].x}) - 1.0f, std::min({c[0].y, c[1].y, c[2].y, c[3].y}) - 1.0f,
              std::max({c[0].x, c[1].x, c[2].x, c[3].x}) + 1.0f, std::max({c[0].y, c[1].y, c[2].y, c[3].y}) + 1.0f};
  }
  const auto on_read_marker = [&](size_t i) {
    const cv::Vec4f& a = box[i];
    return std::any_of(read.begin(), read.end(), [&](size_t k) {
      const cv::Vec4f& b = box[k];
      return a[0] <= b[2] && b[0] <= a[2] && a[1] <= b[3] && b[1] <= a[3] && OnMarker(quads[i], decoded[k]);
    });
  };
  // Read in waves: the finest level first, and within a level the biggest quads first (area bands
  // of a factor 16, so a marker's cells, under 1/16 of its area, come after it). A quad on a marker
  // an earlier wave read (its cells, the same marker at a coarser level) is not read: measured on the
  // 640x480 20-marker renders, 126 of the 263 quads that failed to read were such cells, and a
  // marker read at level 0 was read again at level 1. Skipping them changes no result: a coarser
  // copy that read would lose to the finer one below, and a cell is no marker.
  std::vector<size_t> order(n);
  std::iota(order.begin(), order.end(), 0);
  const auto wave = [&](size_t i) {
    return std::make_pair(quads[i].level, -std::ilogb(std::max(quads[i].area, 1.0f)) / 4);
  };
  std::sort(order.begin(), order.end(),
            [&](size_t a, size_t b) { return std::make_pair(wave(a), a) < std::make_pair(wave(b), b); });
  // Within a wave, a quad around the centre of a smaller one of the same wave (the outline of a
  // marker's quiet zone, about twice its area) waits for the others: on a marker they read, it is
  // not read either. On 640x480 frames of 50 markers 160 of the 182 quads that failed to read were
  // such outlines, read beside their markers. The centres inside a quad's box are looked up among the
  // wave's sorted by x (a wave of gravel or foliage can hold hundreds of quads).
  std::vector<cv::Point2f> centre(n);
  for (size_t i = 0; i < n; ++i) centre[i] = Centre(quads[i].corners);
  std::vector<std::pair<float, size_t>> by_x;  // the wave's quads by their centre's x
  const auto outline = [&](size_t i) {
    const auto from = std::lower_bound(by_x.begin(), by_x.end(), std::make_pair(box[i][0], size_t(0)));
    for (auto c = from; c != by_x.end() && c->first <= box[i][2]; ++c) {
      const size_t j = c->second;
      if (quads[j].area < quads[i].area && StrictlyInside(quads[i].corners, centre[j])) return true;
    }
    return false;
  };
  std::vector<size_t> batch, waiting;
  const auto read_batch = [&]() {
    ParallelFor(cv::Range(0, static_cast<int>(batch.size())), config.threads, [&](const cv::Range& range) {
      for (int b = range.start; b < range.end; ++b) {
        const size_t i = batch[b];
        int id = -1, rotation = 0;
        if (!Identify(grey, quads[i].corners, dictionary, p, id, rotation)) continue;
        auto& corners = decoded[i].corners;
        std::rotate(corners.begin(), corners.begin() + 4 - rotation, corners.end());
        ids[i] = id;
      }
    });
    for (const size_t i : batch) {
      if (ids[i] >= 0) read.push_back(i);
    }
  };
  for (size_t first = 0; first < n;) {
    size_t last = first;
    while (last < n && wave(order[last]) == wave(order[first])) ++last;
    batch.clear();
    waiting.clear();
    by_x.clear();
    for (size_t k = first; k < last; ++k) by_x.emplace_back(centre[order[k]].x, order[k]);
    std::sort(by_x.begin(), by_x.end());
    for (size_t k = first; k < last; ++k) {
      const size_t i = order[k];
      if (!on_read_marker(i)) (outline(i) ? waiting : batch).push_back(i);
    }
    read_batch();
    batch.clear();
    for (const size_t i : waiting) {
      if (!on_read_marker(i)) batch.push_back(i);
    }
    read_batch();
    first = last;
  }
  // Small quads left over, except the cells of markers read and the outlines around them (their
  // quiet zones): every marker of a few cells per side has several, and a second look at each costs
  // more than the search.
  std::vector<int> fragile;
  for (size_t i = 0; i < n; ++i) {
    if (ids[i] < 0 && MeanSide(quads[i].corners) < kSmallCandidateMaxSide && !on_read_marker(i)) {
      fragile.push_back(static_cast<int>(i));
    }
  }
  // A textured frame leaves hundreds (fuzz_core: 1804 on a 49x96 frame, 0.26 s): the biggest
  // kMaxSmallCandidates get their second look, as in the full path (the test frames leave at most 14).
  if (fragile.size() > kMaxSmallCandidates) {
    std::nth_element(fragile.begin(), fragile.begin() + kMaxSmallCandidates, fragile.end(),
                     [&](int a, int b) { return quads[a].area > quads[b].area || (quads[a].area == quads[b].area && a < b); });
    fragile.resize(kMaxSmallCandidates);
  }
  // Quads too close to be two candidates (one small marker's contour traced at two levels, or under
  // two thresholds) are one group, in the order the merge below prefers them (the finer level, then
  // the bigger), and decoded in that order until one reads: a read with cv::aruco's reading wins the
  // merge over any other, so the rest are left; after a second-chance read the rest get only cv::aruco's
  // reading, which would win it. The merge then keeps what it kept when every quad was decoded, save
  // where two quads of a group would read different ids (bench_dump's corpus: the same markers and
  // corners to the bit). Bench's dim distant set: 5 of its 37 second looks went to a marker another
  // quad of the group had read, 4 reading it again (a pattern fit each), one failing every framing
  // (six cell estimates); callgrind of Detect there 114.5 -> 104.8 M.
  std::sort(fragile.begin(), fragile.end(), [&](int a, int b) {
    return std::make_tuple(quads[a].level, -quads[a].area, a) < std::make_tuple(quads[b].level, -quads[b].area, b);
  });
  std::vector<std::vector<int>> groups;
  std::vector<char> grouped(fragile.size(), 0);
  for (size_t f = 0; f < fragile.size(); ++f) {
    if (grouped[f]) continue;
    groups.push_back({fragile[f]});
    for (size_t g = f + 1; g < fragile.size(); ++g) {
      if (!grouped[g] && TooClose(quads[fragile[f]], quads[fragile[g]], p.minMarkerDistanceRate)) {
        grouped[g] = 1;
        groups.back().push_back(fragile[g]);
      }
    }
  }
  SecondLooks looks;
  ParallelFor(cv::Range(0, static_cast<int>(groups.size())), config.threads, [&](const cv::Range& range) {
    for (int k = range.start; k < range.end; ++k) {
      bool second_read = false;
      for (const int i : groups[k]) {
        int id = -1;
        bool second = false;
        if (!DecodeSmallQuad(pyramid, config, dictionary, p, quads[i], !second_read, decoded[i], id, second, checked[i],
                             looks)) {
          continue;
        }
        ids[i] = id;
        second_chance[i] = second;
        if (!second) break;
        second_read = true;
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
  const int cells = dictionary.markerSize + 2 * p.markerBorderBits;
  std::vector<Found> found(kept.size());
  ParallelFor(cv::Range(0, static_cast<int>(kept.size())), config.threads, [&](const cv::Range& range) {
    for (int i = range.start; i < range.end; ++i) {
      Quad q = decoded[kept[i]];
      const bool second = second_chance[kept[i]];
      found[i].id = ids[kept[i]];
      found[i].checked = checked[kept[i]];
      // A full-resolution contour's corners are within the edge fit's reach: where that fit settles
      // (one more pass would move no corner by over kEdgeFitSettledPx) it has reached the fixed point
      // it would reach from cv::aruco's corners too, and tracing cv::aruco's windows around the marker
      // (CornersAsOpenCv) is not needed. A marker under kSettleMinSide that does not settle takes that
      // one more pass and keeps its corners: tracing cv::aruco's windows and fitting its edges again
      // from there cost more than the pass, and gave no better corners (bench_detect, every set: the
      // same ids; corner medians within 0.001 px, 640x480/50 p95 0.172 -> 0.170 px; callgrind of
      // Detect on 640x480/50 176.1 -> 168.1 M). Larger markers that do not settle still start from
      // cv::aruco's corners: on the printed markers of the OpenCV tutorial photos the edge fit does not
      // settle everywhere, and one more pass from its own start ended up to 0.33 px from where it ends
      // from cv::aruco's (the full search keeps to 0.1 px; test_fast_path).
      // Otherwise: cornerSubPix lands within a few hundredths of a pixel from any start a pixel or two
      // away; the edge fit keeps its start where it cannot measure an edge, so it gets cv::aruco's.
      if (config.corner_refinement == CornerRefinement::kEdge && !second && q.level == 0) {
        std::array<cv::Point2f, 4> corners = q.corners;
        if (RefineCornersOnEdgesSettled(grey, corners, cells, kEdgeFitSettledPx,
                                        MeanSide(q.corners) < kSettleMinSide)) {
          found[i].corners = corners;
          found[i].edges_fitted = true;
          continue;
        }
      }
      const bool exact = !subpix && (second || CornersAsOpenCv(pyramid, config, q));
      found[i].corners = q.corners;
      if (exact) continue;
      if (subpix) {
        // From cv::aruco's corners where it has them, as the full path (Detect) refines them: a window
        // fitted to the cells has a narrow reach, and ChArUco markers, with chessboard squares at
        // their corners, end up at another point from a start a pixel away.
        if (!second && CornersAsOpenCv(pyramid, config, q)) found[i].corners = q.corners;
        RefineMarkerCorners(grey, found[i].corners, cells, p.cornerRefinementWinSize, p.cornerRefinementMaxIterations,
                            p.cornerRefinementMinAccuracy);
        continue;
      }
      for (auto& c : found[i].corners) {
        c = RefineCorner(grey, c, p.cornerRefinementWinSize, p.cornerRefinementMaxIterations,
                         p.cornerRefinementMinAccuracy);
      }
    }
  });
  return found;
}

}  // namespace arucotag::internal

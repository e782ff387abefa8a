// Border following (Suzuki & Abe 1985, without the hierarchy) for the candidate search. It gives
// what cv::findContours(RETR_LIST, CHAIN_APPROX_NONE) gives, at less cost per border: a thresholded
// frame has thousands of borders (noise specks, texture), most a few pixels long, and OpenCV spends
// more on each one's sequence, memory arena and bounding box than on following it (callgrind, bench
// set 640x480 with one marker: 23.7k borders in 6 frames, about 790 instructions each). Here a
// border's points go to one reused vector, and the caller measures only the borders it keeps. The
// raster scan between borders tests 32 (AVX2), 16 (SSE2) or 8 pixels at a time for a border's start
// instead of stopping at every change of value, most of which are borders already followed, and the
// search for a border's next pixel is straight-line code per direction it came from, which jumps to
// the next pixel's own code (perf, 640x480, 720p and distant renders: 0.38 -> 0.22 -> 0.18 ms a
// frame, the same borders; the jumps: a quarter fewer instructions following).
#include "contours.hpp"

#include "geometry.hpp"

#include <algorithm>
#include <cstdint>
#include <cstdlib>
#include <cstring>
#include <utility>

#if defined(__SSE2__)
#include <emmintrin.h>
#endif
#if defined(ARUCOTAG_HAND_AVX2)
#include <immintrin.h>
#endif

namespace arucotag::internal {

namespace {

// Marks left on followed border pixels. A pixel whose right neighbour was looked at and found
// background gets kRightEdge (a hole border may start right of it only when it is unmarked or
// kVisited); any other foreground pixel of a border gets kVisited. The values are those
// cv::findContours leaves, so a scan reading them takes the same decisions.
constexpr uchar kVisited = 2;
constexpr uchar kRightEdge = 0x82;

// Direction s: 0 right, then counter-clockwise (y grows downwards), 45 degrees a step.
constexpr int kDx[8] = {1, 1, 0, -1, -1, -1, 0, 1};
constexpr int kDy[8] = {0, -1, -1, -1, 0, 1, 1, 1};

#if defined(ARUCOTAG_HAND_AVX2)
// NextStart's test on blocks of 32 pixels: the first start in them, or, when there is none, -1 - the
// x where fewer than 32 pixels are left.
ARUCOTAG_AVX2 int StartIn32PixelBlocks(const uchar* row, int x, int end) {
  const __m256i zero = _mm256_setzero_si256(), one = _mm256_set1_epi8(1);
  for (; x + 32 <= end; x += 32) {
    const __m256i here = _mm256_loadu_si256(reinterpret_cast<const __m256i*>(row + x));
    const __m256i left = _mm256_loadu_si256(reinterpret_cast<const __m256i*>(row + x - 1));
    const __m256i outer = _mm256_and_si256(_mm256_cmpeq_epi8(left, zero), _mm256_cmpeq_epi8(here, one));
    const __m256i hole = _mm256_and_si256(_mm256_cmpeq_epi8(here, zero), _mm256_cmpgt_epi8(left, zero));
    const unsigned starts = static_cast<unsigned>(_mm256_movemask_epi8(_mm256_or_si256(outer, hole)));
    if (starts != 0) return x + __builtin_ctz(starts);
  }
  return -1 - x;
}
#endif

// Where a border starts, reading the row as it stands (marks included): at x with its left neighbour
// background and x unmarked foreground (an outer border), or x background and its left neighbour
// unmarked or kVisited foreground (a hole). Pixel values are kBackground (0), kForeground (1),
// kVisited (2) and kRightEdge (0x82): bit 0 is set only on kForeground, bit 7 only on kRightEdge.
// The first such x in [x, end), or `end`. Most changes along a row are borders already followed, so
// the row is tested for starts a block at a time rather than stopping at every change.
int NextStart(const uchar* row, int x, int end) {
#if defined(ARUCOTAG_HAND_AVX2)
  // Half the steps of SSE2's blocks below: the scan was over half of the border following's
  // instructions on 1080p frames.
  if (CpuHasAvx2()) {
    const int found = StartIn32PixelBlocks(row, x, end);
    if (found >= 0) return found;
    x = -1 - found;
  }
#endif
#if defined(__SSE2__)
  // Sixteen pixels a step where SSE2 is (every x86-64).
  const __m128i zero = _mm_setzero_si128(), one = _mm_set1_epi8(1);
  for (; x + 16 <= end; x += 16) {
    const __m128i here = _mm_loadu_si128(reinterpret_cast<const __m128i*>(row + x));
    const __m128i left = _mm_loadu_si128(reinterpret_cast<const __m128i*>(row + x - 1));
    const __m128i outer = _mm_and_si128(_mm_cmpeq_epi8(left, zero), _mm_cmpeq_epi8(here, one));
    // kForeground or kVisited: positive as signed bytes (kRightEdge is negative).
    const __m128i hole = _mm_and_si128(_mm_cmpeq_epi8(here, zero), _mm_cmpgt_epi8(left, zero));
    const int starts = _mm_movemask_epi8(_mm_or_si128(outer, hole));
    if (starts != 0) return x + __builtin_ctz(static_cast<unsigned>(starts));
  }
#endif
  // Eight pixels a step in a 64-bit word (the rest of the row there, the whole row elsewhere): bit 7
  // of each byte of `starts` says whether a border starts at that pixel.
  constexpr uint64_t kLow7 = 0x7f7f7f7f7f7f7f7fULL, kBit7 = 0x8080808080808080ULL, kBit0 = 0x0101010101010101ULL;
  for (; x + 8 <= end; x += 8) {
    uint64_t here, left;
    std::memcpy(&here, row + x, sizeof(here));
    std::memcpy(&left, row + x - 1, sizeof(left));
    // Bit 7 set where the pixel is nonzero (every nonzero value has a bit below 7: no carry out).
    const uint64_t here_set = ((here & kLow7) + kLow7) & kBit7, left_set = ((left & kLow7) + kLow7) & kBit7;
    const uint64_t outer = ~left_set & (here & kBit0) << 7;      // background, then kForeground
    const uint64_t hole = ~here_set & left_set & ~left & kBit7;  // kForeground or kVisited, then background
    const uint64_t starts = outer | hole;
    // Little-endian: the lowest set byte is the leftmost pixel.
    if (starts != 0) return x + (__builtin_ctzll(starts) >> 3);
  }
  for (; x < end; ++x) {
    const uchar left = row[x - 1], here = row[x];
    if ((left == kBackground && here == kForeground) ||
        (here == kBackground && (left == kForeground || left == kVisited))) {
      return x;
    }
  }
  return end;
}

// The neighbour of `here` in direction D (0 right, counter-clockwise), as a constant displacement
// from the pixel or from the rows above (`up`) and below (`down`) it.
template <int D>
ARUCOTAG_INLINE uchar At(const uchar* here, const uchar* up, const uchar* down) {
  switch (D & 7) {
    case 0: return here[1];
    case 1: return up[1];
    case 2: return up[0];
    case 3: return up[-1];
    case 4: return here[-1];
    case 5: return down[-1];
    case 6: return down[0];
    default: return down[1];
  }
}

// The step to the neighbour in direction D (0 right, counter-clockwise) of a row `step` bytes long.
constexpr ptrdiff_t Offset(int d, ptrdiff_t step) { return kDx[d & 7] + kDy[d & 7] * step; }

// Points Follow's buffer holds at first (it doubles when a border outgrows it).
constexpr size_t kFirstBufferPoints = 256;

// Follow's buffer (never empty) doubled, out of line: a border rarely outgrows it; `out`, where the
// next point goes, moved with it.
__attribute__((noinline)) cv::Point* Grow(std::vector<cv::Point>& buffer, cv::Point* out) {
  const size_t used = static_cast<size_t>(out - buffer.data());
  buffer.resize(2 * buffer.size());
  return buffer.data() + used;
}

// Follow's move from `here` to its neighbour in direction D & 7, D being the direction the previous
// pixel lies in (Back) plus the steps turned counter-clockwise to the first foreground neighbour:
// marks `here` (kRightEdge when the search passed direction 0, D > 8, which is then background),
// records it at `out`, and moves on; true when the border is closed instead (back at the start,
// about to repeat its first step). The point, the output position and its end are locals of Follow
// (registers): kept in a vector's end pointer and a point passed by reference (push_back), every
// pixel's mark, a byte store that may alias anything, made the compiler store and reload them, a
// chain through memory from pixel to pixel. The same borders; time of Detect (the libraries
// alternated 8 times, median ms a frame) 640x480 with 20 markers 1.316 -> 1.296, with one 0.435 ->
// 0.424, 1080p with one 1.680 -> 1.652, the dim distant set 1.790 -> 1.764, the 640x480 photos 2.109
// -> 2.083, for 1.5 % more instructions (callgrind, 640x480 with 20 markers: 72.60 -> 73.70 M).
template <int D>
ARUCOTAG_INLINE bool Move(uchar*& here, ptrdiff_t step, const uchar* start, const uchar* last, int& x, int& y,
                          cv::Point*& out, cv::Point*& room, std::vector<cv::Point>& buffer) {
  uchar* const next = here + Offset(D, step);
  if (D > 8) {
    *here = kRightEdge;
  } else if (*here == kForeground) {
    *here = kVisited;
  }
  if (out == room) {
    out = Grow(buffer, out);
    room = buffer.data() + buffer.size();
  }
  *out++ = cv::Point(x, y);
  x += kDx[D & 7];
  y += kDy[D & 7];
  if (next == start && here == last) return true;
  here = next;
  return false;
}

// One state of Follow's loop per direction BACK the previous pixel lies in: counter-clockwise from
// direction BACK + 1, the first foreground neighbour (BACK + 8 is BACK itself, foreground: the pixel
// came from there), straight-line tests with the directions known at compile time; each followed by
// its Move and a jump to the state of the pixel moved to, whose previous pixel lies in the opposite
// direction (NEXTk, checked in each turn, is BACK + k + 4 mod 8). Every direction is a constant in its
// state's code and the next state a direct jump, where a loop that switched on the direction at every
// pixel and read the step's offset and coordinates from tables spent a quarter of its instructions on
// that (callgrind of Detect on 640x480 with five markers: following 6.11 -> 4.59 M, the same borders).
#define ARUCOTAG_FOLLOW_TURN(BACK, K, NEXT)                                                   \
  static_assert(NEXT == (BACK + K + 4) % 8, "the state after turning K steps from BACK");   \
  if (K == 8 || At<BACK + K>(here, up, down) != kBackground) {                             \
    if (Move<BACK + K>(here, step, start, last, x, y, out, room, buffer)) return finish(); \
    goto from_##NEXT;                                                                        \
  }
#define ARUCOTAG_FOLLOW_FROM(BACK, NEXT1, NEXT2, NEXT3, NEXT4, NEXT5, NEXT6, NEXT7, NEXT8) \
  from_##BACK : {                                                                          \
    const uchar *up = here - step, *down = here + step;                                    \
    ARUCOTAG_FOLLOW_TURN(BACK, 1, NEXT1)                                                   \
    ARUCOTAG_FOLLOW_TURN(BACK, 2, NEXT2)                                                   \
    ARUCOTAG_FOLLOW_TURN(BACK, 3, NEXT3)                                                   \
    ARUCOTAG_FOLLOW_TURN(BACK, 4, NEXT4)                                                   \
    ARUCOTAG_FOLLOW_TURN(BACK, 5, NEXT5)                                                   \
    ARUCOTAG_FOLLOW_TURN(BACK, 6, NEXT6)                                                   \
    ARUCOTAG_FOLLOW_TURN(BACK, 7, NEXT7)                                                   \
    /* The previous pixel is foreground: the search ends there at the latest. */          \
    ARUCOTAG_FOLLOW_TURN(BACK, 8, NEXT8)                                                   \
  }

// Follows the border through `start` (at `pt` in output coordinates), an outer border's leftmost
// top pixel or the foreground pixel left of a hole's, clockwise around the foreground, marking it.
// Its points go to the front of `buffer` (grown as needed, never shrunk); returns their count.
int Follow(uchar* start, ptrdiff_t step, cv::Point pt, bool hole, std::vector<cv::Point>& buffer) {
  const ptrdiff_t offset[8] = {Offset(0, step), Offset(1, step), Offset(2, step), Offset(3, step),
                               Offset(4, step), Offset(5, step), Offset(6, step), Offset(7, step)};
  if (buffer.empty()) buffer.resize(kFirstBufferPoints);
  cv::Point* out = buffer.data();
  cv::Point* room = buffer.data() + buffer.size();
  int x = pt.x, y = pt.y;
  const auto finish = [&] { return static_cast<int>(out - buffer.data()); };

  // The last foreground neighbour before the border's first step, searched clockwise from the
  // side the scan came from (left of an outer border, right of a hole's pixel).
  const int from = hole ? 0 : 4;
  int s = from;
  uchar* last;
  do {
    s = (s - 1) & 7;
    last = start + offset[s];
  } while (*last == kBackground && s != from);
  if (s == from) {  // an isolated pixel
    *start = kRightEdge;
    *out++ = pt;
    return 1;
  }

  // Counter-clockwise from the previous pixel's direction to the next foreground neighbour, pixel
  // after pixel, until the border closes.
  uchar* here = start;
  switch (s) {
    case 0: goto from_0;
    case 1: goto from_1;
    case 2: goto from_2;
    case 3: goto from_3;
    case 4: goto from_4;
    case 5: goto from_5;
    case 6: goto from_6;
    default: goto from_7;
  }
  ARUCOTAG_FOLLOW_FROM(0, 5, 6, 7, 0, 1, 2, 3, 4)
  ARUCOTAG_FOLLOW_FROM(1, 6, 7, 0, 1, 2, 3, 4, 5)
  ARUCOTAG_FOLLOW_FROM(2, 7, 0, 1, 2, 3, 4, 5, 6)
  ARUCOTAG_FOLLOW_FROM(3, 0, 1, 2, 3, 4, 5, 6, 7)
  ARUCOTAG_FOLLOW_FROM(4, 1, 2, 3, 4, 5, 6, 7, 0)
  ARUCOTAG_FOLLOW_FROM(5, 2, 3, 4, 5, 6, 7, 0, 1)
  ARUCOTAG_FOLLOW_FROM(6, 3, 4, 5, 6, 7, 0, 1, 2)
  ARUCOTAG_FOLLOW_FROM(7, 4, 5, 6, 7, 0, 1, 2, 3)
}
#undef ARUCOTAG_FOLLOW_FROM
#undef ARUCOTAG_FOLLOW_TURN

// The index after i on a ring of `count` indices.
int NextOnRing(int i, int count) { return i + 1 == count ? 0 : i + 1; }

}  // namespace

BorderScan::BorderScan(cv::Mat& binary, std::vector<cv::Point>& buffer)
    : data_(binary.data), step_(binary.step[0]), rows_(binary.rows), cols_(binary.cols), buffer_(buffer) {
  CV_Assert(binary.type() == CV_8UC1 && binary.rows >= 2 && binary.cols >= 2);
}

bool BorderScan::Next() {
  // Scan inside the frame (its column 0 is background, so every pixel scanned has a left neighbour).
  const int end = cols_ - 1;
  for (; y_ < rows_ - 1; ++y_) {
    uchar* row = data_ + y_ * step_;
    x_ = NextStart(row, x_, end);
    if (x_ < end) {
      hole_ = row[x_] == kBackground;
      const int x = x_ - (hole_ ? 1 : 0);
      size_ = Follow(row + x, static_cast<ptrdiff_t>(step_), cv::Point(x - 1, y_ - 1), hole_, buffer_);
      ++x_;
      return true;
    }
    x_ = 1;
  }
  size_ = 0;
  return false;
}

bool BorderScan::Next(std::vector<cv::Point>& points) {
  if (!Next()) return false;
  points.assign(this->points(), this->points() + size_);
  return true;
}

namespace {

// Measure's two passes, plain loops the compiler vectorises (built for AVX2 too): the bounding box,
// then the shoelace sum, with each term's products in 32 bits where every coordinate is under 2^15
// in magnitude (products under 2^30, their difference under 2^31; a border's are, in any image under
// 32k pixels a side) and in 64 bits otherwise. Integer sums, so the same in any order.
ARUCOTAG_VECTOR_CLONES cv::Rect BoxOf(const cv::Point* p, int n) {
  int x0 = p[0].x, x1 = x0, y0 = p[0].y, y1 = y0;
  for (int i = 1; i < n; ++i) {
    x0 = std::min(x0, p[i].x);
    x1 = std::max(x1, p[i].x);
    y0 = std::min(y0, p[i].y);
    y1 = std::max(y1, p[i].y);
  }
  return cv::Rect(x0, y0, x1 - x0 + 1, y1 - y0 + 1);
}
// The shoelace sum with each term's products in T (the closing term first, so that the loop's
// indices are affine and it vectorises).
template <class T>
ARUCOTAG_INLINE int64_t TwiceAreaOf(const cv::Point* p, int n) {
  const auto term = [p](int a, int b) {
    return static_cast<int64_t>(static_cast<T>(p[a].x) * p[b].y - static_cast<T>(p[a].y) * p[b].x);
  };
  int64_t twice = term(n - 1, 0);
  for (int i = 1; i < n; ++i) twice += term(i - 1, i);
  return twice;
}
ARUCOTAG_VECTOR_CLONES int64_t TwiceArea(const cv::Point* p, int n, int32_t) { return TwiceAreaOf<int32_t>(p, n); }
int64_t TwiceArea(const cv::Point* p, int n, int64_t) { return TwiceAreaOf<int64_t>(p, n); }

}  // namespace

Outline Measure(const std::vector<cv::Point>& points) {
  Outline outline;
  if (points.empty()) return outline;
  const int n = static_cast<int>(points.size());
  outline.box = BoxOf(points.data(), n);
  const cv::Rect& b = outline.box;
  constexpr int kSmall = 1 << 15;
  const bool small = b.x > -kSmall && b.y > -kSmall && b.x + b.width <= kSmall && b.y + b.height <= kSmall;
  outline.twice_area = small ? TwiceArea(points.data(), n, int32_t()) : TwiceArea(points.data(), n, int64_t());
  return outline;
}

namespace {

// The distances of ApproximatePolygon's searches, in integers of type T, from every point of [lo, hi)
// into d, returning the largest of them and `largest`: squared distances from `o`, or distances from
// the line through `o` along (cx, cy) times that vector's length. Plain loops the compiler vectorises
// for 32-bit T (built for AVX2 too); where the largest is is found afterwards by a scan that stops at
// it, rather than carried from point to point.
template <class T>
ARUCOTAG_INLINE T SquaredDistancesOf(const cv::Point* p, int lo, int hi, cv::Point o, T* d, T largest) {
  for (int i = lo; i < hi; ++i) {
    const T dx = p[i].x - o.x, dy = p[i].y - o.y;
    d[i] = dx * dx + dy * dy;
    largest = std::max(largest, d[i]);
  }
  return largest;
}
template <class T>
ARUCOTAG_INLINE T ChordDistancesOf(const cv::Point* p, int lo, int hi, cv::Point o, T cx, T cy, T* d, T largest) {
  for (int i = lo; i < hi; ++i) {
    d[i] = std::abs((p[i].y - o.y) * cx - (p[i].x - o.x) * cy);
    largest = std::max(largest, d[i]);
  }
  return largest;
}
ARUCOTAG_VECTOR_CLONES int32_t SquaredDistances(const cv::Point* p, int lo, int hi, cv::Point o, int32_t* d,
                                                int32_t largest) {
  return SquaredDistancesOf(p, lo, hi, o, d, largest);
}
ARUCOTAG_VECTOR_CLONES int32_t ChordDistances(const cv::Point* p, int lo, int hi, cv::Point o, int32_t cx,
                                              int32_t cy, int32_t* d, int32_t largest) {
  return ChordDistancesOf(p, lo, hi, o, cx, cy, d, largest);
}
int64_t SquaredDistances(const cv::Point* p, int lo, int hi, cv::Point o, int64_t* d, int64_t largest) {
  return SquaredDistancesOf(p, lo, hi, o, d, largest);
}
int64_t ChordDistances(const cv::Point* p, int lo, int hi, cv::Point o, int64_t cx, int64_t cy, int64_t* d,
                       int64_t largest) {
  return ChordDistancesOf(p, lo, hi, o, cx, cy, d, largest);
}

// The first index of [lo, hi) whose value in d is `value`, or hi. Eight values are compared at once
// (a loop the compiler vectorises) before the one holding it is looked into: a test per value ended
// in a mispredicted branch and ran at a value a cycle.
template <class T>
ARUCOTAG_INLINE int FirstIn(const T* d, int lo, int hi, T value) {
  constexpr int kBlock = 8;
  int i = lo;
  for (; i + kBlock <= hi; i += kBlock) {
    bool any = false;
    for (int k = 0; k < kBlock; ++k) any |= d[i + k] == value;
    if (any) break;
  }
  for (; i < hi; ++i) {
    if (d[i] == value) return i;
  }
  return hi;
}

// The first index of [lo0, hi0) then [lo1, hi1) whose value in d is `value`, or -1.
template <class T>
int FirstOf(const T* d, int lo0, int hi0, int lo1, int hi1, T value) {
  const int first = FirstIn(d, lo0, hi0, value);
  if (first < hi0) return first;
  const int second = FirstIn(d, lo1, hi1, value);
  return second < hi1 ? second : -1;
}

// The indices after a and before b on a ring of `count` (with a == b, all but a), as two ranges in
// ring order.
ARUCOTAG_INLINE void RingRanges(int a, int b, int count, int& lo0, int& hi0, int& lo1, int& hi1) {
  lo0 = a + 1;
  hi0 = a < b ? b : count;
  lo1 = 0;
  hi1 = a < b ? 0 : b;
}

// ApproximatePolygon's vertices before its clean-up, with distances in T.
template <class T>
void DouglasPeucker(const cv::Point* p, int count, double eps2, std::vector<cv::Point>& polygon) {
  thread_local std::vector<T> distances;
  distances.resize(static_cast<size_t>(count));
  T* d = distances.data();
  int lo0, hi0, lo1, hi1;

  // Two points far apart: from point 0 the farthest point, from that one the farthest, and again.
  // Distances are exact in integers; ties keep the first.
  int from = 0, offset = 0;
  bool within = false;
  for (int round = 0; round < 3; ++round) {
    from = (from + offset) % count;
    const cv::Point o = p[from];
    RingRanges(from, from, count, lo0, hi0, lo1, hi1);
    const T farthest = SquaredDistances(p, lo1, hi1, o, d, SquaredDistances(p, lo0, hi0, o, d, T(0)));
    const int far_at = farthest > 0 ? FirstOf(d, lo0, hi0, lo1, hi1, farthest) : -1;
    if (far_at >= 0) offset = far_at > from ? far_at - from : far_at + count - from;
    within = static_cast<double>(farthest) <= eps2;
  }

  // Douglas-Peucker on the two arcs between them, depth first, the arc from `from` first: an arc
  // whose farthest point from its chord is within epsilon contributes its first point.
  thread_local std::vector<std::pair<int, int>> arcs;
  arcs.clear();
  if (within) {
    polygon.push_back(p[from]);
  } else {
    const int to = (offset + from) % count;
    arcs.emplace_back(to, from);
    arcs.emplace_back(from, to);
  }
  while (!arcs.empty()) {
    const auto [a, b] = arcs.back();
    arcs.pop_back();
    int split = -1;
    if (NextOnRing(a, count) != b) {
      const cv::Point o = p[a];
      const T dx = p[b].x - o.x, dy = p[b].y - o.y;
      RingRanges(a, b, count, lo0, hi0, lo1, hi1);
      // The distance from the chord times the chord's length.
      const T farthest = ChordDistances(p, lo1, hi1, o, dx, dy, d, ChordDistances(p, lo0, hi0, o, dx, dy, d, T(0)));
      // Where the farthest point is, only when the arc is split there (not for an arc within epsilon).
      const double far = static_cast<double>(farthest);
      if (farthest > 0 && far * far > eps2 * (static_cast<double>(dx) * dx + static_cast<double>(dy) * dy)) {
        split = FirstOf(d, lo0, hi0, lo1, hi1, farthest);
      }
    }
    if (split < 0) {
      polygon.push_back(p[a]);
    } else {
      arcs.emplace_back(split, b);
      arcs.emplace_back(a, split);
    }
  }
}

}  // namespace

void ApproximatePolygon(const std::vector<cv::Point>& points, double epsilon, std::vector<cv::Point>& polygon) {
  polygon.clear();
  const int count = static_cast<int>(points.size());
  if (count == 0) return;
  const double eps2 = epsilon * epsilon;
  // Two points of a closed chain of `count` unit steps are at most count / 2 apart along either axis:
  // under 2^15 points every product of coordinate differences is under 2^28, and 32 bits hold each
  // distance exactly.
  if (count < (1 << 15)) {
    DouglasPeucker<int32_t>(points.data(), count, eps2, polygon);
  } else {
    DouglasPeucker<int64_t>(points.data(), count, eps2, polygon);
  }

  // Clean-up, in place and cyclically: a vertex within epsilon / sqrt(2) of the chord between its
  // neighbours, between them along it, and whose chord is not axis-parallel, is dropped.
  const int n = static_cast<int>(polygon.size());
  int kept = n;
  int read = n - 1;
  cv::Point start = polygon[read];
  read = NextOnRing(read, n);
  int write = read;
  cv::Point mid = polygon[read];
  read = NextOnRing(read, n);
  for (int i = 0; i < n && kept > 2; ++i) {
    const cv::Point end = polygon[read];
    read = NextOnRing(read, n);
    const int64_t dx = end.x - start.x, dy = end.y - start.y;
    const int64_t cross = std::abs(static_cast<int64_t>(mid.x - start.x) * dy - static_cast<int64_t>(mid.y - start.y) * dx);
    const int64_t along = static_cast<int64_t>(mid.x - start.x) * (end.x - mid.x) +
                          static_cast<int64_t>(mid.y - start.y) * (end.y - mid.y);
    const double off = static_cast<double>(cross);
    if (off * off <= 0.5 * eps2 * static_cast<double>(dx * dx + dy * dy) && dx != 0 && dy != 0 && along >= 0) {
      --kept;
      polygon[write] = start = end;
      write = NextOnRing(write, n);
      mid = polygon[read];
      read = NextOnRing(read, n);
      ++i;
      continue;
    }
    polygon[write] = start = mid;
    write = NextOnRing(write, n);
    mid = end;
  }
  polygon.resize(kept);
}

}  // namespace arucotag::internal

// Border following (Suzuki & Abe 1985, without the hierarchy) for the candidate search. It gives
// what cv::findContours(RETR_LIST, CHAIN_APPROX_NONE) gives, at less cost per border: a thresholded
// frame has thousands of borders (noise specks, texture), most a few pixels long, and OpenCV spends
// more on each one's sequence, memory arena and bounding box than on following it (callgrind, bench
// set 640x480 with one marker: 23.7k borders in 6 frames, about 790 instructions each). Here a
// border's points go to one reused vector, and the caller measures only the borders it keeps.
#include "contours.hpp"

#include <algorithm>
#include <cstdint>
#include <cstring>

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

// The first x in [x, end) whose pixel differs from `value`, or `end`: eight pixels a step.
int SkipRun(const uchar* row, int x, int end, uchar value) {
  const uint64_t repeated = 0x0101010101010101ULL * value;
  for (; x + 8 <= end; x += 8) {
    uint64_t word;
    std::memcpy(&word, row + x, sizeof(word));
    const uint64_t differ = word ^ repeated;
    if (differ != 0) {
      // Little-endian: the lowest set byte is the leftmost pixel.
      return x + (__builtin_ctzll(differ) >> 3);
    }
  }
  while (x < end && row[x] == value) ++x;
  return x;
}

// Follows the border through `start` (at `pt` in output coordinates), an outer border's leftmost
// top pixel or the foreground pixel left of a hole's, clockwise around the foreground, marking it.
void Follow(uchar* start, ptrdiff_t step, cv::Point pt, bool hole, std::vector<cv::Point>& points) {
  // Neighbour offsets for directions 0..7, twice, so a search may run on past direction 7.
  const ptrdiff_t offset[16] = {1, 1 - step, -step, -1 - step, -1, step - 1, step, step + 1,
                                1, 1 - step, -step, -1 - step, -1, step - 1, step, step + 1};
  points.clear();

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
    points.push_back(pt);
    return;
  }

  uchar* here = start;
  for (;;) {
    // Counter-clockwise from the previous pixel's direction to the next foreground neighbour. The
    // previous pixel is foreground, so the search ends within eight directions.
    const int back = s;
    uchar* next;
    do {
      next = here + offset[++s];
    } while (*next == kBackground);
    s &= 7;
    if (static_cast<unsigned>(s - 1) < static_cast<unsigned>(back)) {
      *here = kRightEdge;  // the search passed direction 0: the right neighbour is background
    } else if (*here == kForeground) {
      *here = kVisited;
    }
    points.push_back(pt);
    pt.x += kDx[s];
    pt.y += kDy[s];
    if (next == start && here == last) break;  // back at the start, about to repeat its first step
    here = next;
    s = (s + 4) & 7;
  }
}

}  // namespace

BorderScan::BorderScan(cv::Mat& binary)
    : data_(binary.data), step_(binary.step[0]), rows_(binary.rows), cols_(binary.cols) {
  CV_Assert(binary.type() == CV_8UC1 && binary.rows >= 2 && binary.cols >= 2);
}

bool BorderScan::Next(std::vector<cv::Point>& points) {
  // Scan inside the frame; a border starts where the row changes from background to unmarked
  // foreground (an outer border) or from unmarked or kVisited foreground to background (a hole).
  const int end = cols_ - 1;
  for (; y_ < rows_ - 1; ++y_) {
    uchar* row = data_ + y_ * step_;
    for (; (x_ = SkipRun(row, x_, end, prev_)) < end; ++x_) {
      const uchar p = row[x_];
      const bool outer = prev_ == kBackground && p == kForeground;
      const bool hole = p == kBackground && (prev_ == kForeground || prev_ == kVisited);
      if (outer || hole) {
        const int x = x_ - (hole ? 1 : 0);
        Follow(row + x, static_cast<ptrdiff_t>(step_), cv::Point(x - 1, y_ - 1), hole, points);
        prev_ = row[x_];  // as marked now
        ++x_;
        return true;
      }
      prev_ = p;
    }
    x_ = 1;
    prev_ = kBackground;
  }
  return false;
}

}  // namespace arucotag::internal

// A dictionary's codes packed into 64-bit words for look-ups by XOR and popcount (internal to
// arucotag_core), shared by the candidate reading (identify.cpp) and the second-chance decoder
// (decode_small.cpp).
#pragma once

#include <cstdint>
#include <vector>

#include <opencv2/aruco.hpp>

namespace arucotag::internal {

/// Bits set in x (no popcnt instruction in the x86-64 baseline this is built for; GCC compiles this
/// idiom to one in the AVX2 clones of the code scans below).
inline int PopCount(uint64_t x) {
  x = x - ((x >> 1) & 0x5555555555555555ULL);
  x = (x & 0x3333333333333333ULL) + ((x >> 2) & 0x3333333333333333ULL);
  x = (x + (x >> 4)) & 0x0f0f0f0f0f0f0f0fULL;
  return static_cast<int>((x * 0x0101010101010101ULL) >> 56);
}

/// Every code of a dictionary in each of its four rotations, packed as cv::aruco packs a marker's
/// bits (Dictionary::getByteListFromBits: row by row, each byte filled from its low end).
struct DictionaryCodes {
  const uchar* data = nullptr;
  int rows = 0, cols = 0;
  // The bytes of every (rows / 16)th marker, as they were when the codes were made: a dictionary
  // changed in place at the same address differs there (see CodesOf).
  std::vector<uchar> sampled;
  std::vector<uint64_t> code;  // 4 per marker: rotations 0..3
};

/// The codes of `dictionary`, cached per thread for the last dictionary seen.
const DictionaryCodes& CodesOf(const cv::aruco::Dictionary& dictionary);

/// The first marker of `codes` (in id order) one of whose rotations lies within `max_distance` bits
/// of `candidate`, and the rotation nearest it (the first of equals); -1 if none. With `max_distance`
/// the dictionary's correction this is Dictionary::identify.
int FirstCodeWithin(const DictionaryCodes& codes, uint64_t candidate, int max_distance, int& rotation);

/// How many codes (each marker in each rotation) agree with `code` on the bits set in `known` but
/// for at most `allowed`, counted up to two; `match` is the index into codes.code of the last one.
int CountCodesAgreeing(const DictionaryCodes& codes, uint64_t code, uint64_t known, int allowed, size_t& match);

/// `bits` (row-major, one per cell of the marker's code, 0 or 1) packed as DictionaryCodes are.
uint64_t PackBits(const unsigned char* bits, int count);

}  // namespace arucotag::internal

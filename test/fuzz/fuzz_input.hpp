#pragma once

// Reads a fuzzer's bytes as typed values, the way libFuzzer's FuzzedDataProvider does, but small
// enough to build with gcc too: the corpus replay (replay.cpp) compiles the harnesses without clang.
// Past the end every read returns zeros, so every input is a valid (if short) program.
#include <algorithm>
#include <cmath>
#include <cstddef>
#include <cstdint>
#include <cstring>
#include <limits>
#include <string>
#include <vector>

namespace arucotag::fuzz {

class FuzzInput {
 public:
  FuzzInput(const std::uint8_t* data, std::size_t size) : data_(data), size_(size) {}

  std::size_t remaining() const { return size_ - at_; }
  const std::uint8_t* position() const { return data_ + at_; }

  std::uint8_t Byte() { return at_ < size_ ? data_[at_++] : 0; }
  bool Bool() { return Byte() & 1; }

  template <class T>
  T Raw() {
    T value{};
    const std::size_t n = std::min(sizeof(T), remaining());
    if (n) std::memcpy(&value, data_ + at_, n);
    at_ += n;
    return value;
  }

  /// An integer in [lo, hi] (two bytes of entropy: plenty for sizes and indices).
  int Int(int lo, int hi) {
    const auto span = static_cast<std::uint64_t>(static_cast<std::int64_t>(hi) - lo) + 1;
    return static_cast<int>(lo + static_cast<std::int64_t>(Raw<std::uint16_t>() % span));
  }

  /// One of the values that break numeric code (NaN, +-inf, 0, -0, tiny, huge, denormal), an
  /// ordinary value near `typical`, or any 8 bytes as a double.
  double Double(double typical = 1.0) {
    static const double kSpecial[] = {std::numeric_limits<double>::quiet_NaN(),
                                      std::numeric_limits<double>::infinity(),
                                      -std::numeric_limits<double>::infinity(),
                                      0.0,
                                      -0.0,
                                      1.0,
                                      -1.0,
                                      1e-300,
                                      std::numeric_limits<double>::denorm_min(),
                                      1e300,
                                      -1e300,
                                      std::numeric_limits<double>::max(),
                                      std::numeric_limits<double>::lowest(),
                                      1e-9,
                                      1e9};
    const std::uint8_t kind = Byte();
    if (kind < 64) return kSpecial[kind % (sizeof(kSpecial) / sizeof(kSpecial[0]))];
    if (kind < 192) return typical * (Raw<std::int16_t>() / 8192.0);  // within +-4x typical
    return Raw<double>();
  }

  std::string String(std::size_t max_length) {
    const std::size_t n = std::min<std::size_t>(Byte() % (max_length + 1), remaining());
    std::string s(reinterpret_cast<const char*>(data_ + at_), n);
    at_ += n;
    return s;
  }

  /// The rest of the input.
  std::vector<std::uint8_t> Rest() {
    std::vector<std::uint8_t> rest(data_ + at_, data_ + size_);
    at_ = size_;
    return rest;
  }

 private:
  const std::uint8_t* data_;
  std::size_t size_;
  std::size_t at_ = 0;
};

}  // namespace arucotag::fuzz

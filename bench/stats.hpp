// What the benchmark tools share to measure and report: process CPU time, percentiles, JSON numbers.
#pragma once

#include <algorithm>
#include <cmath>
#include <ctime>
#include <sstream>
#include <string>
#include <vector>

namespace arucotag::bench {

// The process's CPU time (ms): at one thread the work itself, without the waits for a core that wall
// time includes on a loaded machine.
inline double CpuMs() {
  timespec t{};
  clock_gettime(CLOCK_PROCESS_CPUTIME_ID, &t);
  return t.tv_sec * 1e3 + t.tv_nsec * 1e-6;
}

// The q-quantile (0..1) of `v`, interpolated linearly between the two nearest ranks; NaN for no
// values (a set whose frames were all lost has no time, not a time of 0 ms).
inline double Percentile(std::vector<double> v, double q) {
  if (v.empty()) return NAN;
  std::sort(v.begin(), v.end());
  const double pos = q * (v.size() - 1);
  const size_t i = static_cast<size_t>(pos);
  const double f = pos - i;
  return i + 1 < v.size() ? v[i] * (1 - f) + v[i + 1] * f : v[i];
}

// A JSON number with six significant digits, or null for NaN and infinities (which JSON has no
// spelling for).
inline std::string JsonNumber(double x) {
  if (!std::isfinite(x)) return "null";
  std::ostringstream s;
  s.precision(6);
  s << x;
  return s.str();
}

}  // namespace arucotag::bench

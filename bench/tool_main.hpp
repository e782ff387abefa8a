// The benchmark tools' main(): their Main, with an exception reported as "<tool>: <what>" and exit 1.
#pragma once

#include <cstdio>
#include <exception>

namespace arucotag::bench {

inline int RunTool(const char* tool, int (*tool_main)(int, char**), int argc, char** argv) {
  try {
    return tool_main(argc, argv);
  } catch (const std::exception& e) {
    std::fprintf(stderr, "%s: %s\n", tool, e.what());
    return 1;
  }
}

}  // namespace arucotag::bench

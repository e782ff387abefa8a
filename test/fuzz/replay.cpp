// Replays a harness's checked-in corpus (test/fuzz/corpus/<harness>) through its
// LLVMFuzzerTestOneInput in the normal gcc build: one gtest case per file, so `make test`,
// `make sanitize` and CI run every input the fuzzer kept, in seconds, without clang. A crash or a
// sanitizer report fails the run; an exception other than arucotag::Error (which the harnesses
// catch) fails the case.
#include <algorithm>
#include <cctype>
#include <cstddef>
#include <cstdint>
#include <filesystem>
#include <fstream>
#include <iterator>
#include <string>
#include <vector>

#include <gtest/gtest.h>

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size);

namespace {

namespace fs = std::filesystem;

std::vector<std::string> CorpusFiles() {
  std::vector<std::string> files;
  for (const auto& entry : fs::directory_iterator(ARUCOTAG_FUZZ_CORPUS)) {
    if (entry.is_regular_file()) files.push_back(entry.path().filename().string());
  }
  std::sort(files.begin(), files.end());
  return files;
}

class Corpus : public ::testing::TestWithParam<std::string> {};

TEST_P(Corpus, RunsClean) {
  std::ifstream file(fs::path(ARUCOTAG_FUZZ_CORPUS) / GetParam(), std::ios::binary);
  ASSERT_TRUE(file) << GetParam();
  const std::vector<std::uint8_t> bytes((std::istreambuf_iterator<char>(file)), std::istreambuf_iterator<char>());
  EXPECT_NO_THROW(LLVMFuzzerTestOneInput(bytes.data(), bytes.size()));
}

// Names are file names (hashes, or regress_* for the inputs of fixed defects): gtest allows only
// alphanumerics and underscores.
std::string CaseName(const ::testing::TestParamInfo<std::string>& info) {
  std::string name = info.param;
  std::replace_if(name.begin(), name.end(), [](char c) { return !std::isalnum(static_cast<unsigned char>(c)); }, '_');
  return name;
}

INSTANTIATE_TEST_SUITE_P(Fuzz, Corpus, ::testing::ValuesIn(CorpusFiles()), CaseName);

TEST(CorpusDirectory, HoldsSeeds) { EXPECT_GE(CorpusFiles().size(), 3u) << ARUCOTAG_FUZZ_CORPUS; }

}  // namespace

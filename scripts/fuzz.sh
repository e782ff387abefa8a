#!/usr/bin/env bash
# `make fuzz`: builds the libFuzzer harnesses (test/fuzz/fuzz_*.cpp) with clang, ASan and UBSan
# into their own folder (${ARUCOTAG_BUILD}-fuzz, never the normal build) and runs each for
# FUZZ_SECONDS (default 600) from the checked-in corpus (test/fuzz/corpus/<harness>), with
# -rss_limit_mb=512 -timeout=1: an input that crashes, trips a sanitizer, throws anything but
# arucotag::Error, takes over 1 s or needs over 512 MB is a finding. Prints per harness the runs,
# coverage and findings (inputs in <build>/artifacts/<harness>/) and fails if there is any.
#
# FUZZ_HARNESSES picks some (default: core pose ros config). New inputs go to
# <build>/corpus/<harness>, not the source tree; FUZZ_MERGE=1 afterwards minimizes seeds plus
# new inputs (-merge=1) back into test/fuzz/corpus/<harness>. The normal build replays that
# corpus with gcc as the gtests test_fuzz_<harness> (cmake/fuzz.cmake): no clang needed in CI.
set -uo pipefail
here="$(cd "$(dirname "$0")" && pwd)"
source "${here}/env.sh"
FUZZ_BUILD="${ARUCOTAG_FUZZ_BUILD:-${ARUCOTAG_BUILD}-fuzz}"
FUZZ_SECONDS="${FUZZ_SECONDS:-600}"
FUZZ_HARNESSES="${FUZZ_HARNESSES:-core pose ros config}"
FUZZ_MAX_LEN="${FUZZ_MAX_LEN:-16384}"
# The ROS logs and ROS_HOME of anything the harnesses touch stay in the fuzz build.
export ROS_HOME="${FUZZ_BUILD}/ros_home" ROS_LOG_DIR="${FUZZ_BUILD}/ros_home/log"

fail() {
  echo "fuzz: $*"
  exit 1
}
command -v clang++ > /dev/null || fail "clang++ not found (scripts/install_deps.sh installs clang and libclang-rt-dev)"

SAN_FLAGS="-fsanitize=address,undefined -fno-sanitize-recover=undefined -fno-omit-frame-pointer"
mkdir -p "${FUZZ_BUILD}"
cd "${FUZZ_BUILD}" || exit 1
if [ ! -f Makefile ]; then
  # -O1 -g: readable stacks. -fsanitize=fuzzer-no-link instruments every object for coverage;
  # only the harness executables link libFuzzer's main (cmake/fuzz.cmake). No tests here.
  CC=clang CXX=clang++ cmake "${ARUCOTAG_SRC}" -DCATKIN_DEVEL_PREFIX="${FUZZ_BUILD}/devel" \
    -DPYTHON_EXECUTABLE=/usr/bin/python3 -DCMAKE_BUILD_TYPE=Fuzz -DCATKIN_ENABLE_TESTING=OFF -DARUCOTAG_FUZZ=ON \
    -DCMAKE_CXX_FLAGS_FUZZ="-O1 -g -fsanitize=fuzzer-no-link ${SAN_FLAGS}" \
    -DCMAKE_C_FLAGS_FUZZ="-O1 -g -fsanitize=fuzzer-no-link ${SAN_FLAGS}" \
    -DCMAKE_EXE_LINKER_FLAGS_FUZZ="${SAN_FLAGS}" -DCMAKE_SHARED_LINKER_FLAGS_FUZZ="${SAN_FLAGS}" \
    -DCMAKE_MODULE_LINKER_FLAGS_FUZZ="${SAN_FLAGS}" || fail "cmake failed"
fi
targets=()
for name in ${FUZZ_HARNESSES}; do targets+=("fuzz_${name}"); done
make -j"$(nproc)" "${targets[@]}" || fail "build failed"

# ASan's quarantine holds freed memory back (256 MB by default) to catch use after free; over a fork job's
# hundreds of inputs it fills with earlier frames and RSS passes 512 MB with no input needing it (the whole
# core corpus, 838 inputs, in one process: 518 MB and an "oom" with the default, at most 133 MB without
# quarantine, 272 MB with 64 MB of it).
# 64 MB keeps the check and leaves -rss_limit_mb measuring what one input needs.
export ASAN_OPTIONS="abort_on_error=1:detect_leaks=1:quarantine_size_mb=64"
export UBSAN_OPTIONS="halt_on_error=1:print_stacktrace=1"
summary=()
findings=0
for name in ${FUZZ_HARNESSES}; do
  exe="$(find "${FUZZ_BUILD}/devel" "${FUZZ_BUILD}" -name "fuzz_${name}" -type f -executable -print -quit)"
  [ -n "${exe}" ] || fail "fuzz_${name} was not built"
  seeds="${ARUCOTAG_SRC}/test/fuzz/corpus/${name}"
  work="${FUZZ_BUILD}/corpus/${name}"
  artifacts="${FUZZ_BUILD}/artifacts/${name}"
  log="${FUZZ_BUILD}/fuzz_${name}.log"
  rm -rf "${artifacts}"
  mkdir -p "${seeds}" "${work}" "${artifacts}"
  echo "fuzz: ${name} for ${FUZZ_SECONDS} s (log ${log})"
  # -fork=1: one child process at a time does the fuzzing, so a finding is saved and counted and the
  # run goes on for its whole time instead of stopping at the first one.
  "${exe}" -fork=1 -ignore_crashes=1 -ignore_timeouts=1 -ignore_ooms=1 -max_total_time="${FUZZ_SECONDS}" \
    -rss_limit_mb=512 -timeout=1 -max_len="${FUZZ_MAX_LEN}" -artifact_prefix="${artifacts}/" \
    "${work}" "${seeds}" > "${log}" 2>&1
  status=$?
  if [ "${FUZZ_MERGE:-0}" = 1 ]; then
    merged="${FUZZ_BUILD}/merged/${name}"
    rm -rf "${merged}" && mkdir -p "${merged}"
    "${exe}" -merge=1 -rss_limit_mb=512 -timeout=1 -max_len="${FUZZ_MAX_LEN}" "${merged}" "${seeds}" "${work}" \
      >> "${log}" 2>&1 && find "${seeds}" -type f ! -name 'regress_*' -delete && cp "${merged}"/* "${seeds}/"
  fi
  # The fork mode's status lines: "#<runs>: cov: <edges> ft: <features> corp: ... oom/timeout/crash: a/b/c ...".
  last=$(grep -E '^#[0-9]+: cov:' "${log}" | tail -1)
  runs=$(sed -E 's/^#([0-9]+):.*/\1/' <<< "${last}")
  cov=$(grep -oE 'cov: [0-9]+ ft: [0-9]+' <<< "${last}")
  read -r oom slow crashes < <(grep -oE 'oom/timeout/crash: [0-9]+/[0-9]+/[0-9]+' <<< "${last}" | grep -oE '[0-9]+/[0-9]+/[0-9]+' | tr / ' ')
  crashes=${crashes:-0} slow=${slow:-0} oom=${oom:-0}
  # A finding the last status line has not counted yet is still in the artifacts (leaks are crashes).
  count() { find "${artifacts}" -type f \( "$@" \) | wc -l; }
  max() { echo $(($1 > $2 ? $1 : $2)); }
  crashes=$(max "${crashes}" "$(count -name 'crash-*' -o -name 'leak-*' -o -name 'deadly*')")
  slow=$(max "${slow}" "$(count -name 'timeout-*' -o -name 'slow-unit-*')")
  oom=$(max "${oom}" "$(count -name 'oom-*')")
  if [ "${status}" -ne 0 ] && [ $((crashes + slow + oom)) -eq 0 ]; then crashes=1; fi
  findings=$((findings + crashes + slow + oom))
  summary+=("$(printf '%-7s runs %10s  %-18s  crashes %d  slow %d  oom %d' \
    "${name}" "${runs:-0}" "${cov:-cov: ?}" "${crashes}" "${slow}" "${oom}")")
  for artifact in "${artifacts}"/*; do
    [ -e "${artifact}" ] && echo "fuzz: ${name} finding ${artifact}"
  done
done
echo "fuzz: ${FUZZ_SECONDS} s per harness (-rss_limit_mb=512 -timeout=1)"
printf '%s\n' "${summary[@]}"
if [ "${findings}" -ne 0 ]; then
  echo "fuzz: ${findings} finding(s); reproduce with <build>/devel/lib/arucotag/fuzz_<harness> <artifact>"
  exit 1
fi
echo "fuzz: no findings"

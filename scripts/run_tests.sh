#!/usr/bin/env bash
# Builds and runs every test (gtests and rostests), then prints "N passed, N failed" counted from
# catkin's JUnit XML. Exits non-zero on any failure, or when no test ran.
set -uo pipefail
source "$(dirname "$0")/env.sh"
cd "${ARUCOTAG_BUILD}" || exit 1
rm -rf test_results
make -j"$(nproc)" tests || { echo "0 passed, 1 failed"; exit 1; }
arucotag_source_devel
make run_tests -j1
catkin_test_results --verbose "${ARUCOTAG_BUILD}/test_results" > test_summary.txt 2>&1 || true
tail -n 5 test_summary.txt
/usr/bin/python3 "${ARUCOTAG_SRC}/scripts/count_results.py" "${ARUCOTAG_BUILD}/test_results"

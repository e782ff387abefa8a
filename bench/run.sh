#!/usr/bin/env bash
# `make bench`: times (a) cv::aruco defaults, (b) Detect, (c) the per-frame pipeline and (d) the
# nodelet in a manager on the same frames, prints the markdown table and writes
# $ARUCOTAG_BUILD/bench/results.{json,md}. Frame sets are rendered once into $ARUCOTAG_BUILD/bench/frames.
#
# Environment: BENCH_FRAMES (rendered scenes per synthetic set, default 6), BENCH_REPS (passes,
# default 8; the 100-frame sequence gets half), BENCH_THREADS (OpenCV threads, default all).
set -euo pipefail
source "$(dirname "$0")/../scripts/env.sh"
BIN="${ARUCOTAG_DEVEL}/lib/arucotag"
OUT="${ARUCOTAG_BUILD}/bench"
mkdir -p "${OUT}/frames" "${ROS_LOG_DIR}"
FRAMES="${BENCH_FRAMES:-6}"
REPS="${BENCH_REPS:-8}"
COMMON=(--data "${ARUCOTAG_SRC}/test/data" --cache "${OUT}/frames" --frames "${FRAMES}" --sequence-frames 100
        --reps "${REPS}")

echo "== (a)-(c): bench_detect (first run renders the frame sets, about a minute)"
THREADS=()
if [ -n "${BENCH_THREADS:-}" ]; then THREADS=(--threads "${BENCH_THREADS}"); fi
"${BIN}/bench_detect" "${COMMON[@]}" "${THREADS[@]}" --json "${OUT}/detect.json"

echo "== (d): bench_nodelet (nodelet::Loader in process, private ROS master)"
rm -f "${OUT}/nodelet.json"
if [ -x "${BIN}/bench_nodelet" ]; then
  arucotag_source_devel
  # A master of our own on a free port, so a running roscore is neither needed nor disturbed.
  PORT=$(/usr/bin/python3 -c 'import socket; s = socket.socket(); s.bind(("", 0)); print(s.getsockname()[1])')
  export ROS_MASTER_URI="http://localhost:${PORT}"
  rosmaster --core -p "${PORT}" > "${ROS_LOG_DIR}/bench_master.log" 2>&1 &
  MASTER=$!
  trap 'kill "${MASTER}" 2>/dev/null || true' EXIT
  for _ in $(seq 50); do
    if rosparam list > /dev/null 2>&1; then break; fi
    sleep 0.2
  done
  "${BIN}/bench_nodelet" "${COMMON[@]}" --json "${OUT}/nodelet.json" || echo "bench_nodelet failed: (d) left out"
  kill "${MASTER}" 2>/dev/null || true
  wait "${MASTER}" 2>/dev/null || true
  trap - EXIT
else
  echo "bench_nodelet not built (no nodelet target): (d) left out"
fi

echo
echo "== pose trust: bench_pose (BENCH_POSE_FRAMES rendered frames, default 1000)"
"${BIN}/bench_pose" --frames "${BENCH_POSE_FRAMES:-1000}" --json "${OUT}/pose.json" | tee "${OUT}/pose.md"

echo
/usr/bin/python3 "${ARUCOTAG_SRC}/bench/report.py" "${OUT}/detect.json" "${OUT}/nodelet.json" \
  --out-json "${OUT}/results.json" --out-md "${OUT}/results.md"
echo
echo "Written: ${OUT}/results.json, ${OUT}/results.md"

#!/usr/bin/env bash
# `make bench`: times OpenCV's detectMarkers (defaults: the reference), its ArUco3 mode, AprilTag 3
# (tag36h11 sets), ours (default, fast, video mode), the per-frame pipeline and the nodelet in a
# manager on the same frames, and every corner refinement option of ours against cv::aruco's with the
# same option (scored pass), prints the markdown tables and writes $ARUCOTAG_BUILD/bench/results.{json,md}
# and bench/RESULTS.md. Frame sets are rendered once into $ARUCOTAG_BUILD/bench/frames.
#
# Environment: BENCH_FRAMES (scenes per synthetic and warped set, default 6), BENCH_REPS (passes,
# default 8; the 100-frame sequence gets half), BENCH_THREADS (OpenCV threads, default 1),
# BENCH_ALL_CORES_REPS (more passes at all cores for the OpenCV-threaded detectors, default 2; 0 = off),
# BENCH_RESULTS_MD (where the checked-in table goes, default bench/RESULTS.md; empty = nowhere).
set -euo pipefail
source "$(dirname "$0")/../scripts/env.sh"
BIN="${ARUCOTAG_DEVEL}/lib/arucotag"
OUT="${ARUCOTAG_BUILD}/bench"
mkdir -p "${OUT}/frames" "${ROS_LOG_DIR}"
FRAMES="${BENCH_FRAMES:-6}"
REPS="${BENCH_REPS:-8}"
COMMON=(--data "${ARUCOTAG_SRC}/test/data" --cache "${OUT}/frames" --frames "${FRAMES}" --sequence-frames 100
        --reps "${REPS}")

echo "== detectors: bench_detect (first run renders the frame sets, about a minute)"
"${BIN}/bench_detect" "${COMMON[@]}" --threads "${BENCH_THREADS:-1}" --all-cores-reps "${BENCH_ALL_CORES_REPS:-2}" \
  --json "${OUT}/detect.json"

echo "== nodelet: bench_nodelet (nodelet::Loader in process, private ROS master)"
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
  "${BIN}/bench_nodelet" "${COMMON[@]}" --json "${OUT}/nodelet.json" || echo "bench_nodelet failed: nodelet left out"
  kill "${MASTER}" 2>/dev/null || true
  wait "${MASTER}" 2>/dev/null || true
  trap - EXIT
else
  echo "bench_nodelet not built (no nodelet target): nodelet left out"
fi

echo
/usr/bin/python3 "${ARUCOTAG_SRC}/bench/report.py" "${OUT}/detect.json" "${OUT}/nodelet.json" \
  --out-json "${OUT}/results.json" --out-md "${OUT}/results.md" \
  --command "make bench (BENCH_FRAMES=${FRAMES} BENCH_REPS=${REPS} BENCH_THREADS=${BENCH_THREADS:-1})"
RESULTS_MD="${BENCH_RESULTS_MD-${ARUCOTAG_SRC}/bench/RESULTS.md}"
if [ -n "${RESULTS_MD}" ]; then cp "${OUT}/results.md" "${RESULTS_MD}"; fi
echo
echo "Written: ${OUT}/results.json, ${OUT}/results.md${RESULTS_MD:+, ${RESULTS_MD}}"

# Last, so that the detection table is written even when this is interrupted.
echo
echo "== pose trust: bench_pose (BENCH_POSE_FRAMES rendered frames, default 1000)"
"${BIN}/bench_pose" --frames "${BENCH_POSE_FRAMES:-1000}" --json "${OUT}/pose.json" | tee "${OUT}/pose.md"

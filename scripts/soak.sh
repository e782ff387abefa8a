#!/usr/bin/env bash
# `make soak`: a master and a nodelet manager of its own (free port), then build/devel/lib/arucotag/soak:
# SOAK_SECONDS (default 600) of 1280x720 frames, camera_info and clouds at 30 Hz into the detector
# nodelet, then SOAK_CYCLES (default 100) load/unload cycles with frames flowing. Prints the figures
# and exits non-zero past a budget (RSS growth, unanswered frames, a dead manager). The manager runs with
# MALLOC_ARENA_MAX=1 unless SOAK_MALLOC_ARENA_MAX says otherwise (0: glibc's default).
set -euo pipefail
source "$(dirname "$0")/env.sh"
arucotag_source_devel
mkdir -p "${ROS_LOG_DIR}"
PORT=$(/usr/bin/python3 -c 'import socket; s = socket.socket(); s.bind(("", 0)); print(s.getsockname()[1])')
export ROS_MASTER_URI="http://localhost:${PORT}"
rosmaster --core -p "${PORT}" > "${ROS_LOG_DIR}/soak_master.log" 2>&1 &
MASTER=$!
MANAGER_PID=""
cleanup() {
  [ -n "${MANAGER_PID}" ] && kill "${MANAGER_PID}" 2>/dev/null || true
  kill "${MASTER}" 2>/dev/null || true
  wait 2>/dev/null || true
}
trap cleanup EXIT
for _ in $(seq 50); do
  if rosparam list > /dev/null 2>&1; then break; fi
  sleep 0.2
done
# The manager binary itself (not through rosrun's shell), so /proc/PID is the process holding the nodelet.
MANAGER_BIN="$(catkin_find --first-only nodelet nodelet 2>/dev/null || echo /usr/lib/nodelet/nodelet)"
# With one malloc arena, as the launch files start their managers (their `malloc_arena_max`; README,
# Reliability): SOAK_MALLOC_ARENA_MAX=0 measures glibc's default instead.
ARENAS="${SOAK_MALLOC_ARENA_MAX:-1}"
if [ "${ARENAS}" = 0 ]; then ARENA_ENV=(); else ARENA_ENV=(MALLOC_ARENA_MAX="${ARENAS}"); fi
echo "soak: manager with ${ARENA_ENV[*]:-the default malloc arenas of glibc}"
env "${ARENA_ENV[@]}" "${MANAGER_BIN}" manager __name:=soak_manager > "${ROS_LOG_DIR}/soak_manager.log" 2>&1 &
MANAGER_PID=$!
for _ in $(seq 100); do
  if rosservice list 2>/dev/null | grep -q /soak_manager/load_nodelet; then break; fi
  sleep 0.2
done
"${ARUCOTAG_BUILD}/devel/lib/arucotag/soak" --manager /soak_manager --manager-pid "${MANAGER_PID}" \
  --photo "${ARUCOTAG_SRC}/test/data/ubiquity_fiducials/tag_245-246_d7_14cm.png" \
  --seconds "${SOAK_SECONDS:-600}" --cycles "${SOAK_CYCLES:-100}"

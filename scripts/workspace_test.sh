#!/usr/bin/env bash
# `make workspace-test`: the package as a user gets it, in a fresh catkin workspace (<tmp>/src/arucotag,
# a copy of this checkout without build folders). Runs the README's commands ("In a catkin workspace")
# and checks that each one works:
#   - catkin_make (testing on), then from the devel space, each in a fresh shell environment:
#     rosrun arucotag detector_node, roslaunch arucotag detector.launch (its manager must have
#     MALLOC_ARENA_MAX=1 in its environment), a nodelet manager with
#     `rosrun nodelet nodelet load arucotag/DetectorNodelet`; each gets a real photo
#     (test/data/ubiquity_fiducials/tag_01_d7_14cm.png, DICT_5X5_1000, 0.145 m) and its camera_info
#     from scripts/photo_tags_check.py, which checks that `tags` reports id 1 about 0.73 m away;
#   - catkin_make install, the installed files, and the same three checks with only install/setup.bash
#     sourced (plugin, launch files, config and messages must come from the install space);
#   - catkin_make run_tests and catkin_test_results.
# Writes one JUnit testcase per check (failures carry the reason) to workspace_test.xml in the
# results folder, which scripts/count_results.py counts, and exits non-zero when a check failed.
#
#   scripts/workspace_test.sh [--junit-dir DIR] [--keep]
#
# DIR defaults to $ARUCOTAG_WORKSPACE_JUNIT_DIR, else $ARUCOTAG_BUILD/test_results/workspace (./build
# when unset). The workspace is made under $TMPDIR and removed afterwards unless --keep is given or a
# check failed (its logs are in <workspace>/logs). ccache and make settings pass through
# (CMAKE_CXX_COMPILER_LAUNCHER, CCACHE_*, MAKEFLAGS, ROS_PARALLEL_JOBS).
set -uo pipefail

SRC="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"

# The README's commands, run literally (bash -c) in the workspace folder. The README test below keeps
# README.md and this list the same.
README_BUILD='catkin_make -DPYTHON_EXECUTABLE=/usr/bin/python3'
README_INSTALL='catkin_make install'
README_RUN_TESTS='catkin_make run_tests -j1 && catkin_test_results build/test_results'
README_NODE='rosrun arucotag detector_node image:=/camera/image_raw camera_info:=/camera/camera_info _dictionary:=DICT_5X5_1000 _tag_size:=0.145'
README_CONFIG='cp "$(rospack find arucotag)/config/detector.yaml" my_tags.yaml'
README_LAUNCH='roslaunch arucotag detector.launch camera:=front image:=image_raw config:=$PWD/my_tags.yaml'
README_MANAGER='rosrun nodelet nodelet manager __name:=nodelet_manager'
README_LOAD='rosrun nodelet nodelet load arucotag/DetectorNodelet nodelet_manager __name:=aruco_detector image:=/camera/image_raw camera_info:=/camera/camera_info _dictionary:=DICT_5X5_1000 _tag_size:=0.145'

PHOTO="${SRC}/test/data/ubiquity_fiducials/tag_01_d7_14cm.png"
CAMERA="${SRC}/test/data/ubiquity_fiducials/camera.yaml"
# Truth of the photo (the core's test_real_photos checks the same): id 1, 0.145 m, 0.73 m away.
CHECK_ARGS=(--image "${PHOTO}" --camera-info "${CAMERA}" --id 1 --side 0.145 --distance 0.73 --tolerance 0.02
  --timeout 60)

# ---------------------------------------------------------------------------------------------
# Inner part: `workspace_test.sh --space devel|install WS RESULTS`, started by the outer part in a
# fresh environment (env -i); sources the space's setup.bash and runs the three user checks.
# ---------------------------------------------------------------------------------------------
record() {  # record RESULTS NAME SECONDS MESSAGE: an empty MESSAGE is a pass
  local dir
  dir="$1/$(printf '%02d' "$(find "$1" -mindepth 1 -maxdepth 1 | wc -l)")_$2"
  mkdir -p "${dir}"
  echo "$3" > "${dir}/time"
  printf '%s' "$4" > "${dir}/failure"
  if [ -n "$4" ]; then echo "workspace_test: $2 FAILED: $4" | head -n 5; else echo "workspace_test: $2 ok ($3 s)"; fi
}

if [ "${1:-}" = --space ]; then
  set +u  # setup.bash reads unset variables
  SPACE="$2" WS="$3" RESULTS="$4"
  LOGS="${WS}/logs/${SPACE}"
  mkdir -p "${LOGS}"
  cd "${WS}" || exit 1
  # shellcheck disable=SC1090
  source "${WS}/${SPACE}/setup.bash" || exit 1
  export ROS_HOME="${WS}/ros_home" ROS_LOG_DIR="${WS}/ros_home/log"
  PORT="$(python3 -c 'import socket; s = socket.socket(); s.bind(("localhost", 0)); print(s.getsockname()[1])')"
  export ROS_MASTER_URI="http://localhost:${PORT}"

  pids=()
  stop_all() {  # one at a time, in order: SIGINT (roslaunch and nodelet load clean up on it), then SIGKILL
    # One at a time: a manager stopped while a `nodelet load` client's bond is still open can abort in
    # ~Loader (Debian's nodelet 1.10, ros/nodelet_core#99: 2 of 10 times here), so the client goes first.
    local pid
    for pid in "${pids[@]}"; do
      kill -INT "${pid}" 2>/dev/null
      for _ in $(seq 50); do kill -0 "${pid}" 2>/dev/null || break; sleep 0.2; done
      kill -KILL "${pid}" 2>/dev/null
      wait "${pid}" 2>/dev/null
      local rc=$?
      # Not a failed check (the detector worked), but worth seeing: a crash on Ctrl-C.
      case ${rc} in 134 | 135 | 136 | 139) echo "workspace_test: warning: ${SPACE}: process ${pid} crashed at shutdown (exit ${rc})" ;; esac
    done
    pids=()
  }
  roscore_pid=""
  cleanup() { stop_all; [ -z "${roscore_pid}" ] || { pids=("${roscore_pid}"); stop_all; }; }
  trap cleanup EXIT

  # Where the package must come from: the workspace's source folder (devel) or the install space.
  if [ "${SPACE}" = devel ]; then SHARE="${WS}/src/arucotag"; else SHARE="${WS}/install/share/arucotag"; fi
  t0=${SECONDS}
  problems=()
  found="$(rospack find arucotag 2>&1)"
  [ "${found}" = "${SHARE}" ] || problems+=("rospack find arucotag: '${found}', expected ${SHARE}")
  plugin="$(rospack plugins --attrib=plugin nodelet 2>&1 | grep '^arucotag ')"
  [ "${plugin}" = "arucotag ${SHARE}/nodelet_plugins.xml" ] || problems+=("nodelet plugin: '${plugin}'")
  for f in launch/detector.launch launch/rover.launch launch/replay.launch launch/rviz.launch \
      config/detector.yaml config/urc.yaml config/arucotag.rviz package.xml nodelet_plugins.xml; do
    [ -f "${SHARE}/${f}" ] || problems+=("no ${SHARE}/${f}")
  done
  # Messages and the dynamic_reconfigure module in Python, from this space.
  py="$(python3 -c 'import arucotag.msg, arucotag.cfg.ArucotagDetectorConfig as c; print(arucotag.msg.__file__, c.__file__)' \
    2> "${LOGS}/python.err")"
  case "${py}" in
    "${WS}/${SPACE}/lib/python3/dist-packages/arucotag/msg/__init__.py ${WS}/${SPACE}/lib/python3/dist-packages/arucotag/cfg/ArucotagDetectorConfig.py") ;;
    *) problems+=("python messages / dynamic_reconfigure: '${py}' $(tail -n 3 "${LOGS}/python.err")") ;;
  esac
  for exe in detector_node replay_pacer make_sample_bag detect_image; do
    [ -x "${WS}/${SPACE}/lib/arucotag/${exe}" ] || problems+=("no ${WS}/${SPACE}/lib/arucotag/${exe}")
  done
  for f in lib/libarucotag_nodelet.so lib/libarucotag_core.so include/arucotag/ArucotagDetectorConfig.h \
      include/arucotag/ArucoTagArray.h; do
    [ -f "${WS}/${SPACE}/${f}" ] || problems+=("no ${WS}/${SPACE}/${f}")
  done
  if [ "${SPACE}" = install ]; then
    for f in include/arucotag/detector.hpp include/arucotag/ros/messages.hpp share/arucotag/cmake/arucotagConfig.cmake; do
      [ -f "${WS}/install/${f}" ] || problems+=("no ${WS}/install/${f}")
    done
  fi
  record "${RESULTS}" "${SPACE}_package_files" $((SECONDS - t0)) "$(printf '%s\n' "${problems[@]}")"

  roscore -p "${PORT}" > "${LOGS}/roscore.log" 2>&1 &
  roscore_pid=$!
  for _ in $(seq 100); do rosnode list > /dev/null 2>&1 && break; sleep 0.2; done

  # check NAME TAGS_TOPIC IMAGE_TOPIC INFO_TOPIC [MANAGER]: processes in pids are up; publish, check, stop.
  # MANAGER: a nodelet manager the launch file started, which must run with one malloc arena.
  check() {
    local name="$1" t0=${SECONDS} out
    out="$(python3 "${SRC}/scripts/photo_tags_check.py" "${CHECK_ARGS[@]}" --tags-topic "$2" --image-topic "$3" \
      --camera-info-topic "$4" 2>&1)"
    local rc=$?
    if [ ${rc} -eq 0 ] && [ -n "${5:-}" ]; then
      local pid
      pid="$(rosnode info "$5" 2>/dev/null | awk '/^Pid:/ {print $2}')"
      if ! tr '\0' '\n' < "/proc/${pid:-0}/environ" 2>/dev/null | grep -qx 'MALLOC_ARENA_MAX=1'; then
        out+=$'\n'"$5 (pid '${pid}') does not run with MALLOC_ARENA_MAX=1 (the launch file's malloc_arena_max)"
        rc=1
      fi
    fi
    echo "${out}" > "${LOGS}/${name}_check.log"
    stop_all
    if [ ${rc} -eq 0 ]; then
      record "${RESULTS}" "${SPACE}_${name}" $((SECONDS - t0)) ""
    else
      record "${RESULTS}" "${SPACE}_${name}" $((SECONDS - t0)) "$(printf '%s\n--- %s:\n%s' "$(echo "${out}" | tail -n 3)" \
        "${name} log" "$(tail -n 15 "${LOGS}/${name}.log")")"
    fi
  }

  bash -c "${README_NODE}" > "${LOGS}/rosrun_detector_node.log" 2>&1 &
  pids+=($!)
  check rosrun_detector_node /tags /camera/image_raw /camera/camera_info

  # The README's config step: copy the installed example, set the photo's dictionary and marker side.
  bash -c "${README_CONFIG}" && sed -i -e 's/^dictionary: [A-Z0-9_]*/dictionary: DICT_5X5_1000/' \
    -e 's/^tag_size: [0-9.]*/tag_size: 0.145/' my_tags.yaml
  bash -c "${README_LAUNCH}" > "${LOGS}/roslaunch_detector.log" 2>&1 &
  pids+=($!)
  check roslaunch_detector /front/tags /front/image_raw /front/camera_info /front/aruco_detector_manager

  bash -c "${README_MANAGER}" > "${LOGS}/nodelet_load.log" 2>&1 &
  pids+=($!)
  bash -c "${README_LOAD}" >> "${LOGS}/nodelet_load.log" 2>&1 &
  pids=($! "${pids[@]}")  # unload the nodelet before the manager stops
  check nodelet_load /tags /camera/image_raw /camera/camera_info
  exit 0
fi

# ---------------------------------------------------------------------------------------------
# Outer part.
# ---------------------------------------------------------------------------------------------
JUNIT_DIR="${ARUCOTAG_WORKSPACE_JUNIT_DIR:-${ARUCOTAG_BUILD:-${SRC}/build}/test_results/workspace}"
KEEP=false
while [ $# -gt 0 ]; do
  case "$1" in
    --junit-dir) JUNIT_DIR="$2"; shift 2 ;;
    --keep) KEEP=true; shift ;;
    *) echo "usage: $0 [--junit-dir DIR] [--keep]" >&2; exit 2 ;;
  esac
done
mkdir -p "${JUNIT_DIR}"
JUNIT_DIR="$(cd "${JUNIT_DIR}" && pwd)"
JUNIT="${JUNIT_DIR}/workspace_test.xml"
rm -f "${JUNIT}"

WS="$(mktemp -d "${TMPDIR:-/tmp}/arucotag_ws.XXXXXX")"
RESULTS="${WS}/results"
LOGS="${WS}/logs"
mkdir -p "${WS}/src/arucotag" "${RESULTS}" "${LOGS}"
echo "workspace_test: workspace ${WS}, results ${JUNIT}"
START=${SECONDS}

# A fresh environment for every step, as a new terminal would have: Debian's ROS lives in /usr, so
# PATH needs nothing else; build caching and job settings pass through.
CLEAN_ENV=(env -i HOME="${HOME}" PATH=/usr/bin:/bin LANG=C.UTF-8 TMPDIR="${TMPDIR:-/tmp}")
for var in CMAKE_CXX_COMPILER_LAUNCHER CCACHE_DIR CCACHE_BASEDIR MAKEFLAGS ROS_PARALLEL_JOBS; do
  [ -z "${!var:-}" ] || CLEAN_ENV+=("${var}=${!var}")
done
CLEAN_ENV+=(ROS_HOME="${WS}/ros_home")

step() {  # step NAME LOG SETUP COMMAND: runs COMMAND (bash -c) in the workspace, SETUP sourced first if set
  local name="$1" log="${LOGS}/$2" setup="$3" t0=${SECONDS}
  local cmd="${4}"
  [ -z "${setup}" ] || cmd="source ${setup} && ${cmd}"
  if (cd "${WS}" && "${CLEAN_ENV[@]}" bash -c "${cmd}") > "${log}" 2>&1; then
    record "${RESULTS}" "${name}" $((SECONDS - t0)) ""
    return 0
  fi
  # A test run names its failed cases and why first (count_results.py on the workspace's results).
  local failed_cases=""
  [ ! -d "${WS}/build/test_results" ] || [ "${name}" != run_tests ] ||
    failed_cases="$(/usr/bin/python3 "${SRC}/scripts/count_results.py" "${WS}/build/test_results" 2>&1 >/dev/null)"
  record "${RESULTS}" "${name}" $((SECONDS - t0)) "$(printf '%s failed%s\n%s\nerrors and last lines of %s:\n%s\n...\n%s' \
    "$4" "${failed_cases:+:}" "${failed_cases}" "${log}" "$(grep -m 8 -E -A 3 'Error|error:|FAILURE|FAILED' "${log}")" \
    "$(tail -n 15 "${log}")")"
  return 1
}

# The README commands are the ones tested here.
t0=${SECONDS}
missing=""
for var in README_BUILD README_INSTALL README_RUN_TESTS README_NODE README_CONFIG README_LAUNCH README_MANAGER \
    README_LOAD; do
  grep -qF -- "${!var}" "${SRC}/README.md" || missing+="README.md does not show: ${!var}"$'\n'
done
record "${RESULTS}" readme_shows_tested_commands $((SECONDS - t0)) "${missing}"

# The checkout without build output: git's files plus uncommitted ones, never a folder with a CMake cache.
tar -C "${SRC}" --exclude=./.git --exclude=./output --exclude-tag-all=CMakeCache.txt -cf - . \
  | tar -C "${WS}/src/arucotag" -xf -

if step catkin_make catkin_make.log "" "${README_BUILD} -DCATKIN_ENABLE_TESTING=ON"; then
  "${CLEAN_ENV[@]}" bash "${SRC}/scripts/workspace_test.sh" --space devel "${WS}" "${RESULTS}"
  if step catkin_make_install catkin_make_install.log "" "${README_INSTALL}"; then
    "${CLEAN_ENV[@]}" bash "${SRC}/scripts/workspace_test.sh" --space install "${WS}" "${RESULTS}"
  fi
  step run_tests run_tests.log devel/setup.bash "${README_RUN_TESTS}"
fi
ELAPSED=$((SECONDS - START))

# JUnit XML (scripts/junit.py): one suite, one case per check, the reason in <failure>.
/usr/bin/python3 - "${SRC}/scripts" "${RESULTS}" "${JUNIT}" "${ELAPSED}" <<'EOF'
import pathlib
import sys

sys.path.insert(0, sys.argv[1])
import junit  # noqa: E402 (scripts/junit.py)

results, out, elapsed = pathlib.Path(sys.argv[2]), sys.argv[3], sys.argv[4]
cases = []
for case in sorted(p for p in results.iterdir() if p.is_dir()):
    reason = (case / "failure").read_text(errors="replace")
    cases.append((case.name.split("_", 1)[1], "failure" if reason else None, None, reason,
                  (case / "time").read_text().strip()))
junit.write_suite(out, "arucotag.workspace_test", cases, time=elapsed)
failures = sum(outcome == "failure" for _, outcome, _, _, _ in cases)
print("workspace_test: %d checks, %d failed, %s s; %s" % (len(cases), failures, elapsed, out))
sys.exit(1 if failures or not cases else 0)
EOF
status=$?
if [ ${status} -eq 0 ] && [ "${KEEP}" = false ]; then
  rm -rf "${WS}"
else
  echo "workspace_test: workspace kept in ${WS} (logs in ${LOGS})"
fi
exit ${status}

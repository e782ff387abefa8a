#!/usr/bin/env bash
# Replays a recording with rviz (config/arucotag.rviz) under a virtual X server and saves a
# screenshot of the whole rviz window once playback is over (rviz keeps the last frame: the clock
# stops with the bag). rviz starts first, alone (launch/rviz.launch), and the replay follows once
# its window is up. Exits non-zero when rviz dies in four starts in a row or in two replays, when
# rviz or the replay logs an error, or when the screenshot fails. Logs: <out>.log (the replay),
# <out>_rviz.log (rviz), <out>_roscore.log.
#
#   scripts/rviz_screenshot.sh [--bag FILE] [--out PNG] [--start S] [--duration S] [--bundles YAML]
#
# Defaults: the sample recording ($ARUCOTAG_BUILD/sample/sample.bag), output/rviz/rviz.png, the
# stretch 6.5-10 s where the rover closes in on the post and sees two of its faces, and the sample's
# post as a bundle (config/sample_bundles.yaml; --bundles "" for none).
set -euo pipefail
source "$(dirname "$0")/env.sh"

BAG="${ARUCOTAG_BUILD}/sample/sample.bag"
OUT="${ARUCOTAG_SRC}/output/rviz/rviz.png"
START=6.5
DURATION=3.5
BUNDLES="${ARUCOTAG_SRC}/config/sample_bundles.yaml"
INNER=false
while [ $# -gt 0 ]; do
  case "$1" in
    --bag) BAG="$2"; shift 2 ;;
    --out) OUT="$2"; shift 2 ;;
    --start) START="$2"; shift 2 ;;
    --duration) DURATION="$2"; shift 2 ;;
    --bundles) BUNDLES="$2"; shift 2 ;;
    --inner) INNER=true; shift ;;
    *) echo "usage: $0 [--bag FILE] [--out PNG] [--start S] [--duration S] [--bundles YAML]" >&2; exit 2 ;;
  esac
done
BAG="$(cd "$(dirname "${BAG}")" && pwd)/$(basename "${BAG}")"
mkdir -p "$(dirname "${OUT}")"
OUT="$(cd "$(dirname "${OUT}")" && pwd)/$(basename "${OUT}")"
LOG="${OUT%.png}.log"

if [ "${INNER}" = false ]; then
  [ -f "${BAG}" ] || { echo "rviz_screenshot: no bag at ${BAG} (scripts/demo.sh makes the sample)" >&2; exit 1; }
  # A fresh X server of the window's size; -a picks a free display number.
  exec xvfb-run -a -s "-screen 0 1280x800x24" bash "$0" --inner --bag "${BAG}" --out "${OUT}" \
    --start "${START}" --duration "${DURATION}" --bundles "${BUNDLES}"
fi

arucotag_source_devel
# A private master on a free port: nothing else on the machine sees this replay.
PORT="$(/usr/bin/python3 -c 'import socket; s = socket.socket(); s.bind(("localhost", 0)); print(s.getsockname()[1])')"
export ROS_MASTER_URI="http://localhost:${PORT}"
pids=()
cleanup() {
  for pid in "${pids[@]}"; do kill -INT "${pid}" 2>/dev/null || true; done
  for pid in "${pids[@]}"; do
    for _ in $(seq 50); do kill -0 "${pid}" 2>/dev/null || break; sleep 0.2; done
    kill -KILL "${pid}" 2>/dev/null || true
  done
}
trap cleanup EXIT

roscore -p "${PORT}" > "${LOG%.log}_roscore.log" 2>&1 &
pids+=($!)
for _ in $(seq 100); do rosnode list > /dev/null 2>&1 && break; sleep 0.2; done
# replay.launch sets this too; rviz, started first, must read it when it starts.
rosparam set use_sim_time true
# rviz 1.14 under Xvfb sometimes dies while it starts, with a heap error or a segfault inside rviz,
# more often while the machine is busy: 2 of 7 starts beside the sanitizer build's detector as it
# started, 0 of 35 alone. So rviz starts first, alone, up to four times; it is up once it has
# subscribed to the overlay and is still running 3 s later (its own log lines are no sign: rviz
# buffers its stdout when it is not a terminal). A death after that replays once more. Every death
# is reported on stderr, and each dead rviz's log is kept beside the screenshot.
RVIZ_LOG="${LOG%.log}_rviz.log"
died() { grep -q 'rviz-[0-9]*\] process has died' "${RVIZ_LOG}"; }
# A roslaunch of ours: SIGINT, up to 10 s to end, then SIGKILL.
stop_launch() {
  kill -INT "$1" 2>/dev/null || true
  for _ in $(seq 50); do kill -0 "$1" 2>/dev/null || break; sleep 0.2; done
  kill -KILL "$1" 2>/dev/null || true
  wait "$1" 2>/dev/null || true
}
rviz_launch=""
stop_rviz() {
  [ -n "${rviz_launch}" ] || return 0
  stop_launch "${rviz_launch}"
  rviz_launch=""
}
start_rviz() {  # 0 once rviz is up; 1 when it died first, 2 when it never subscribed
  PYTHONUNBUFFERED=1 roslaunch arucotag rviz.launch > "${RVIZ_LOG}" 2>&1 &
  rviz_launch=$!
  pids=("${rviz_launch}" "${pids[@]}")
  for _ in $(seq 120); do
    if rostopic info /zed/overlay 2>/dev/null | sed -n '/^Subscribers:/,$p' | grep -q '/rviz'; then
      sleep 3
      died && return 1
      return 0
    fi
    died && return 1
    sleep 0.5
  done
  echo "rviz_screenshot: rviz did not subscribe to /zed/overlay in 60 s, see ${RVIZ_LOG}" >&2
  return 2
}
starts=0
up_rviz() {  # rviz running, after at most four starts
  local status
  for _ in 1 2 3 4; do
    starts=$((starts + 1))
    status=0
    start_rviz || status=$?
    [ ${status} -eq 0 ] && return 0
    stop_rviz
    [ ${status} -eq 1 ] || return 1
    mv "${RVIZ_LOG}" "${RVIZ_LOG%.log}_start${starts}.log"
    echo "rviz_screenshot: rviz died while it started (log kept as ${RVIZ_LOG%.log}_start${starts}.log)" >&2
  done
  echo "rviz_screenshot: rviz died in four starts in a row" >&2
  return 1
}
# The player ending is not the detector ending: it can still be working through the images queued
# while rate control let the player run ahead (seconds under the sanitizer, where a CI run drew an
# empty overlay panel). Waits until the overlay topic has been quiet for 2 s (at most 60 s) and prints
# how many overlay images came in meanwhile.
overlay_quiet() {
  /usr/bin/python3 - "$1" <<'PY'
import sys
import time

import rospy
from rospy.msg import AnyMsg

rospy.init_node("rviz_screenshot_wait", anonymous=True, disable_signals=True)
last = [0, time.monotonic()]


def on_overlay(_):
    last[0] += 1
    last[1] = time.monotonic()


sub = rospy.Subscriber(sys.argv[1], AnyMsg, on_overlay)
start = time.monotonic()
while time.monotonic() - last[1] < 2.0 and time.monotonic() - start < 60.0:
    time.sleep(0.1)
sub.unregister()
print(last[0])
PY
}
replay() {  # one replay, rviz already up, to its last frame; 1 when rviz died, 2 on any other failure
  # The loops below read roslaunch's log as it runs: Python must not buffer it until exit.
  PYTHONUNBUFFERED=1 roslaunch arucotag replay.launch bag:="${BAG}" start:="${START}" duration:="${DURATION}" rviz:=false \
    bundles:="${BUNDLES}" rate_control:=true quiet:=true paused:=true > "${LOG}" 2>&1 &
  launch=$!
  pids=("${launch}" "${pids[@]}")
  local advertised=false
  for _ in $(seq 120); do
    if rostopic info /zed/overlay 2>/dev/null | sed -n '/^Publishers:/,/^Subscribers:/p' | grep -q 'aruco_detector_manager'; then
      advertised=true
      break
    fi
    died && return 1
    kill -0 "${launch}" 2>/dev/null || { echo "rviz_screenshot: roslaunch exited early, see ${LOG}" >&2; return 2; }
    sleep 0.5
  done
  [ "${advertised}" = true ] || { echo "rviz_screenshot: the detector never advertised /zed/overlay, see ${LOG}" >&2; return 2; }
  # Registered is not connected: the detector's manager connects to rviz on its own time (slowly in
  # the sanitizer build, whose CI run drew an empty overlay panel), and frames sent before are lost.
  local connected=false
  for _ in $(seq 60); do
    if rosnode info /zed/aruco_detector_manager 2>/dev/null | grep -A1 'topic: /zed/overlay$' | grep -q 'to: /rviz'; then
      connected=true
      break
    fi
    died && return 1
    sleep 0.5
  done
  [ "${connected}" = true ] || echo "rviz_screenshot: the detector never connected to rviz on /zed/overlay" >&2
  local playing=false
  for _ in $(seq 60); do
    if rosservice call /player/pause_playback false > /dev/null 2>&1; then playing=true; break; fi
    died && return 1
    sleep 0.5
  done
  [ "${playing}" = true ] || { echo "rviz_screenshot: cannot start the player, see ${LOG}" >&2; return 2; }
  # Playback is over when the player node has gone (it does not respawn).
  for _ in $(seq 600); do
    grep -q 'player-1\] process has finished' "${LOG}" && break
    died && return 1
    kill -0 "${launch}" 2>/dev/null || { echo "rviz_screenshot: roslaunch exited early, see ${LOG}" >&2; return 2; }
    sleep 0.5
  done
  local late
  late="$(overlay_quiet /zed/overlay 2>/dev/null || echo unknown)"
  echo "rviz_screenshot: ${late} overlay image(s) published after the player ended" >&2
  sleep 3  # let rviz draw the last frame
  died && return 1
  for _ in $(seq 10); do  # rosnode list can time out on a busy machine: ask again
    rosnode list 2>/dev/null | grep -q '^/rviz$' && return 0
    sleep 1
  done
  echo "rviz_screenshot: rviz is not running, see ${LOG}; nodes: $(rosnode list 2>&1 | tr "\n" " ")" >&2
  return 2
}
up_rviz || exit 1
status=0
replay || status=$?
if [ ${status} -eq 1 ]; then
  stop_launch "${launch}"
  mv "${LOG}" "${LOG%.log}_try1.log"
  mv "${RVIZ_LOG}" "${RVIZ_LOG%.log}_try1.log"
  echo "rviz_screenshot: rviz died during the replay (logs kept as ${LOG%.log}_try1.log and ${RVIZ_LOG%.log}_try1.log), replaying once more" >&2
  stop_rviz
  up_rviz || exit 1
  status=0
  replay || status=$?
  [ ${status} -ne 1 ] || echo "rviz_screenshot: rviz died again, see ${RVIZ_LOG}" >&2
fi
[ ${status} -eq 0 ] || exit 1
xwd -root -silent | /usr/bin/convert xwd:- png:"${OUT}"
errors='\[ERROR\]|rviz.*(crash|Segmentation)|process has died'
if grep -E "${errors}" "${LOG}" "${RVIZ_LOG}" > /dev/null; then
  echo "rviz_screenshot: errors in ${LOG} or ${RVIZ_LOG}:" >&2
  grep -E "${errors}" "${LOG}" "${RVIZ_LOG}" | head -5 >&2
  exit 1
fi
echo "rviz_screenshot: ${OUT}"

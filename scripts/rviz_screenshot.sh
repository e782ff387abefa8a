#!/usr/bin/env bash
# Replays a recording with rviz (config/arucotag.rviz) under a virtual X server and saves a
# screenshot of the whole rviz window once playback is over (rviz keeps the last frame: the clock
# stops with the bag). Exits non-zero when rviz dies or logs an error, or the screenshot fails.
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
# rviz needs a few seconds to open under software GL: the player starts paused and plays once
# rviz's overlay display has subscribed. rviz 1.14 under Xvfb very rarely aborts while starting
# (a heap error inside rviz): one more try then, reported on stderr.
start_replay() {
  # The loops below read roslaunch's log as it runs: Python must not buffer it until exit.
  PYTHONUNBUFFERED=1 roslaunch arucotag replay.launch bag:="${BAG}" start:="${START}" duration:="${DURATION}" rviz:=true \
    bundles:="${BUNDLES}" rate_control:=true quiet:=true paused:=true > "${LOG}" 2>&1 &
  launch=$!
  pids=("${launch}" "${pids[@]}")
  for _ in $(seq 120); do
    if rostopic info /zed/overlay 2>/dev/null | grep -q '/rviz'; then return 0; fi
    grep -q 'rviz-[0-9]*\] process has died' "${LOG}" && return 1
    kill -0 "${launch}" 2>/dev/null || return 1
    sleep 0.5
  done
  return 1
}
if ! start_replay; then
  echo "rviz_screenshot: rviz did not come up (log kept as ${LOG%.log}_try1.log), trying once more" >&2
  kill -INT "${launch}" 2>/dev/null || true
  wait "${launch}" 2>/dev/null || true
  mv "${LOG}" "${LOG%.log}_try1.log"
  start_replay || { echo "rviz_screenshot: rviz never subscribed, see ${LOG}" >&2; exit 1; }
fi
playing=false
for _ in $(seq 60); do
  if rosservice call /player/pause_playback false > /dev/null 2>&1; then playing=true; break; fi
  sleep 0.5
done
[ "${playing}" = true ] || { echo "rviz_screenshot: cannot start the player, see ${LOG}" >&2; exit 1; }

# Playback is over when the player node has gone (it does not respawn).
for _ in $(seq 600); do
  grep -q 'player-1\] process has finished' "${LOG}" && break
  kill -0 "${launch}" 2>/dev/null || { echo "rviz_screenshot: roslaunch exited early, see ${LOG}" >&2; exit 1; }
  sleep 0.5
done
sleep 3  # let rviz draw the last frame
rviz_up=false
for _ in $(seq 10); do  # rosnode list can time out on a busy machine: ask again
  if rosnode list 2>/dev/null | grep -q '^/rviz$'; then rviz_up=true; break; fi
  sleep 1
done
if [ "${rviz_up}" = false ]; then
  echo "rviz_screenshot: rviz is not running, see ${LOG}; nodes: $(rosnode list 2>&1 | tr "\n" " ")" >&2
  exit 1
fi
xwd -root -silent | /usr/bin/convert xwd:- png:"${OUT}"
if grep -E '\[ERROR\]|rviz.*(crash|Segmentation)|process has died' "${LOG}" > /dev/null; then
  echo "rviz_screenshot: errors in ${LOG}:" >&2
  grep -E '\[ERROR\]|rviz.*(crash|Segmentation)|process has died' "${LOG}" | head -5 >&2
  exit 1
fi
echo "rviz_screenshot: ${OUT}"

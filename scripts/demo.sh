#!/usr/bin/env bash
# The demo: replays the sample recording (a rover's stereo camera passing a URC post, made by
# make_sample_bag on first use; recorded like a field bag: jpeg images on <image>/compressed,
# camera_info on its own 2 Hz timer, a half-resolution cloud for every third image) through the
# detector nodelet with launch/replay.launch (compressed transport), headless, and scores every
# marker against the recording's truth. Prints the table, then the detector's tracks (`tracks` topic:
# hits, misses, frames to validation, pose), writes a few overlay images to $ARUCOTAG_DEMO_OUT (default
# ./output/demo) and exits non-zero when a marker misses the thresholds (recall >= 90 %, median distance
# error <= 0.5 % of range, median yaw error <= 1 deg) or a track of an id not in the recording is validated.
#
# The detector runs with the rover's preset, config/urc.yaml; ARUCOTAG_DEMO_PARAMS overrides
# detector parameters on top of it (a YAML mapping, e.g. "{corner_refinement: subpix}").
set -euo pipefail
source "$(dirname "$0")/env.sh"
arucotag_source_devel

OUT="${ARUCOTAG_DEMO_OUT:-${ARUCOTAG_SRC}/output/demo}"
BAG="${ARUCOTAG_BUILD}/sample/sample.bag"
GENERATOR="${ARUCOTAG_DEVEL}/lib/arucotag/make_sample_bag"
PARAMS="${ARUCOTAG_DEMO_PARAMS:-{\}}"

# A sample older than the generator may show another scene: make it again.
if [ ! -f "${BAG}" ] || [ "${GENERATOR}" -nt "${BAG}" ]; then
  echo "== Generating the sample recording (15 s at 15 Hz, 1280x720 jpeg, 640x360 clouds at 5 Hz, about 105 MB) into ${BAG}"
  "${GENERATOR}" --output "${BAG}"
fi

echo
echo "== Replaying ${BAG} through launch/replay.launch (config/urc.yaml, overrides: ${PARAMS})"
mkdir -p "${OUT}"
rm -f "${OUT}"/overlay_*.png
/usr/bin/python3 "${ARUCOTAG_SRC}/scripts/replay_report.py" --bag "${BAG}" --own-master --out "${OUT}" \
  --log "${ROS_LOG_DIR}/demo_replay.log" --launch-arg "params:=${PARAMS}"

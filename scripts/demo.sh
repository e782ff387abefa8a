#!/usr/bin/env bash
# The demo: runs detect_image on the bundled real photos with their intrinsics and prints every
# detection with its distance; overlays go to $ARUCOTAG_DEMO_OUT (default ./output/demo).
set -euo pipefail
source "$(dirname "$0")/env.sh"
OUT="${ARUCOTAG_DEMO_OUT:-${ARUCOTAG_SRC}/output/demo}"
BIN="${ARUCOTAG_BUILD}/devel/lib/arucotag/detect_image"
DATA="${ARUCOTAG_SRC}/test/data"
mkdir -p "${OUT}"

echo "== UbiquityRobotics fiducials photos (DICT_5X5_1000, 0.145 m, calibrated Raspberry Pi camera)"
"${BIN}" --dictionary DICT_5X5_1000 --size 0.145 --camera "${DATA}/ubiquity_fiducials/camera.yaml" \
  --output "${OUT}" "${DATA}"/ubiquity_fiducials/*.png
echo
echo "== OpenCV tutorial photos (DICT_6X6_250, ChArUco markers 0.02 m, calibrated camera)"
"${BIN}" --dictionary DICT_6X6_250 --size 0.02 --camera "${DATA}/opencv_tutorial/tutorial_camera_charuco.yml" \
  --output "${OUT}" "${DATA}"/opencv_tutorial/choriginal.jpg "${DATA}"/opencv_tutorial/chocclusion_original.jpg
echo
echo "== OpenCV tutorial single markers (DICT_6X6_250; suggested, unverified intrinsics)"
"${BIN}" --dictionary DICT_6X6_250 --size 0.05 --camera "${DATA}/opencv_tutorial/tutorial_camera_params.yml" \
  --output "${OUT}" "${DATA}"/opencv_tutorial/singlemarkersoriginal.jpg
echo
echo "Overlays written to ${OUT}"

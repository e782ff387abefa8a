#!/usr/bin/env bash
# Installs the Debian 12 packages arucotag needs, only those missing. Safe to run again.
set -euo pipefail

PACKAGES=(
  build-essential cmake pkg-config catkin python3-catkin-pkg python3-empy
  ros-core-dev rosbash libnodeletlib-dev libnodelet-dev libnodeletlib-tools
  libcv-bridge-dev libimage-transport-dev libimage-geometry-dev libcamera-calibration-parsers-dev
  libtf2-ros-dev libtf2-geometry-msgs-dev libmessage-filters-dev
  librostest-dev python3-rostest python3-roslaunch python3-rosbag librosbag-dev python3-roslz4 libroslz4-dev
  python3-rospy python3-sensor-msgs python3-std-msgs python3-geometry-msgs
  libopencv-dev libopencv-contrib-dev libpcl-dev libpcl-conversions-dev
  ros-sensor-msgs ros-geometry-msgs ros-visualization-msgs ros-std-msgs
  libdiagnostic-updater-dev libdynamic-reconfigure-config-init-mutex-dev python3-dynamic-reconfigure
  libgtest-dev googletest libbenchmark-dev
  libapriltag-dev
  clang libclang-rt-14-dev  # make fuzz: libFuzzer and the sanitizer runtimes
  rviz xvfb xauth x11-apps imagemagick
)

missing=()
for pkg in "${PACKAGES[@]}"; do
  if ! dpkg-query -W -f='${Status}' "$pkg" 2>/dev/null | grep -q "install ok installed"; then
    missing+=("$pkg")
  fi
done
if [ ${#missing[@]} -eq 0 ]; then
  echo "install_deps: all ${#PACKAGES[@]} packages present"
  exit 0
fi

SUDO=""
if [ "$(id -u)" -ne 0 ]; then SUDO="sudo"; fi
echo "install_deps: installing ${missing[*]}"
$SUDO apt-get update -qq
# With recommends, as tested: rviz under Xvfb needs the Mesa software GL driver they bring.
$SUDO env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq "${missing[@]}"

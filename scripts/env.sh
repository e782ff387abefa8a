# Sourced by the other scripts: one place for the build folder and the environment ROS tools need.
# pyenv's python3 has no ROS modules; catkin, genmsg and roslaunch need Debian's.
export PATH="/usr/bin:${PATH}"
ARUCOTAG_SRC="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
# ARUCOTAG_BUILD is the package's build folder, ARUCOTAG_DEVEL its devel space. The standalone build
# (scripts/build.sh) keeps both in ./build; a catkin workspace (<ws>/src/arucotag, catkin_make) has
# <ws>/build/arucotag and <ws>/devel, used when there is no ./build. The workspace's tests set both.
if [ -z "${ARUCOTAG_BUILD:-}" ] && [ ! -d "${ARUCOTAG_SRC}/build" ] \
    && [ "$(basename "$(dirname "${ARUCOTAG_SRC}")")" = src ] \
    && [ -d "${ARUCOTAG_SRC}/../../build/arucotag" ] && [ -f "${ARUCOTAG_SRC}/../../devel/setup.bash" ]; then
  ARUCOTAG_WS="$(cd "${ARUCOTAG_SRC}/../.." && pwd)"
  ARUCOTAG_BUILD="${ARUCOTAG_WS}/build/arucotag"
  ARUCOTAG_DEVEL="${ARUCOTAG_DEVEL:-${ARUCOTAG_WS}/devel}"
fi
ARUCOTAG_BUILD="${ARUCOTAG_BUILD:-${ARUCOTAG_SRC}/build}"
ARUCOTAG_DEVEL="${ARUCOTAG_DEVEL:-${ARUCOTAG_BUILD}/devel}"
export ARUCOTAG_SRC ARUCOTAG_BUILD ARUCOTAG_DEVEL
export ROS_HOME="${ROS_HOME:-${ARUCOTAG_BUILD}/ros_home}"
export ROS_LOG_DIR="${ROS_LOG_DIR:-${ROS_HOME}/log}"
arucotag_source_devel() {
  # shellcheck disable=SC1091
  set +u
  source "${ARUCOTAG_DEVEL}/setup.bash"
  set -u
}

# Sourced by the other scripts: one place for the build folder and the environment ROS tools need.
# pyenv's python3 has no ROS modules; catkin, genmsg and roslaunch need Debian's.
export PATH="/usr/bin:${PATH}"
ARUCOTAG_SRC="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
ARUCOTAG_BUILD="${ARUCOTAG_BUILD:-${ARUCOTAG_SRC}/build}"
export ARUCOTAG_SRC ARUCOTAG_BUILD
export ROS_HOME="${ROS_HOME:-${ARUCOTAG_BUILD}/ros_home}"
export ROS_LOG_DIR="${ROS_LOG_DIR:-${ROS_HOME}/log}"
arucotag_source_devel() {
  # shellcheck disable=SC1091
  set +u
  source "${ARUCOTAG_BUILD}/devel/setup.bash"
  set -u
}

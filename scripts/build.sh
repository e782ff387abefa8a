#!/usr/bin/env bash
# Configures and builds the package standalone with catkin into $ARUCOTAG_BUILD (default ./build).
set -euo pipefail
source "$(dirname "$0")/env.sh"
mkdir -p "${ARUCOTAG_BUILD}"
cd "${ARUCOTAG_BUILD}"
if [ ! -f Makefile ]; then
  cmake "${ARUCOTAG_SRC}" -DCATKIN_DEVEL_PREFIX="${ARUCOTAG_DEVEL}" \
    -DPYTHON_EXECUTABLE=/usr/bin/python3 -DCMAKE_BUILD_TYPE=Release -DCATKIN_ENABLE_TESTING=ON
fi
make -j"$(nproc)" "$@"

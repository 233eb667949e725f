#!/usr/bin/env bash
# Configures and builds into build/ (Release, Ninja, ccache). Extra arguments go to CMake's configure step.
set -euo pipefail
root=$(cd "$(dirname "$0")/.." && pwd)
GAPS_CACHE=${GAPS_CACHE:-$HOME/.cache/gaps}
export CCACHE_DIR=${CCACHE_DIR:-$GAPS_CACHE/ccache}
# Paths under the checkout are hashed relative to it, so every clone shares the cache.
export CCACHE_BASEDIR=${CCACHE_BASEDIR:-$root}
build=${GAPS_BUILD_DIR:-$root/build}
jobs=${GAPS_JOBS:-$(nproc)}
if [ ! -f "$build/build.ninja" ] || [ $# -gt 0 ]; then
  cmake -S "$root" -B "$build" -G Ninja -DCMAKE_BUILD_TYPE=Release \
    -DGAPS_PYTHON:FILEPATH="$GAPS_CACHE/venv/bin/python" "$@"
fi
cmake --build "$build" -j "$jobs"

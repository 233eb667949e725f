#!/usr/bin/env bash
# Builds the fuzz targets with clang, libFuzzer and sanitizers (build-fuzz/, or $GAPS_FUZZ_BUILD_DIR) and
# fuzzes each for SECONDS (default 60), two at a time: `bash scripts/fuzz.sh [SECONDS] [ctest -R REGEX]`.
# Prints one line per target with its executions and corpus size; exits non-zero when any target crashed,
# leaking, ran out of memory or hung (the input that did it is named). fuzz/README.md has the longer runs.
set -euo pipefail
root=$(cd "$(dirname "$0")/.." && pwd)
seconds=${1:-60}
shift || true
GAPS_CACHE=${GAPS_CACHE:-$HOME/.cache/gaps}
export CCACHE_DIR=${CCACHE_DIR:-$GAPS_CACHE/ccache}
export CCACHE_BASEDIR=${CCACHE_BASEDIR:-$root}
build=${GAPS_FUZZ_BUILD_DIR:-$root/build-fuzz}
cmake -S "$root" -B "$build" -G Ninja -DCMAKE_BUILD_TYPE=RelWithDebInfo -DCMAKE_CXX_COMPILER=clang++ \
  -DGAPS_FUZZ=ON -DBUILD_TESTING=OFF -DGAPS_FUZZ_SECONDS="$seconds" \
  -DGAPS_PYTHON:FILEPATH="$GAPS_CACHE/venv/bin/python" >/dev/null
cmake --build "$build" -j "${GAPS_JOBS:-$(nproc)}" --target gaps_fuzzers
cd "$build/fuzz"  # the fuzz tests live here (the rest of the fuzz build has no tests)
rm -rf work
ctest -L fuzz -j "${GAPS_FUZZ_JOBS:-2}" --output-on-failure "$@"

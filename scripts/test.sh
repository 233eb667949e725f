#!/usr/bin/env bash
# One command for the whole test suite: install what is missing, build, run ctest (extra arguments go to
# ctest), then one summary line: passed, failed, skipped, and how many of the skipped are GPU tests (label
# gpu) and why they skipped; on a machine without a GPU all of them, for want of a CUDA device. Then the
# fuzz targets, each for GAPS_FUZZ_SECONDS (scripts/fuzz.sh). The exit status is non-zero when either failed.
set -euo pipefail
root=$(cd "$(dirname "$0")/.." && pwd)
bash "$root/scripts/setup.sh"
bash "$root/scripts/build.sh"
build=${GAPS_BUILD_DIR:-$root/build}
cd "$build"
results="$build/Testing/ctest_results.xml"
gpu_tests="$build/Testing/gpu_tests.json"
mkdir -p "$build/Testing"
rm -f "$results"
status=0
ctest --output-on-failure -j "${GAPS_TEST_JOBS:-2}" --output-junit "$results" "$@" || status=$?
ctest --show-only=json-v1 -L gpu >"$gpu_tests"
python3 "$root/tests/scripts/ctest_summary.py" "$results" "$gpu_tests"
# Then every fuzz target for GAPS_FUZZ_SECONDS (default 60; 0 skips), built with clang and sanitizers.
fuzz_seconds=${GAPS_FUZZ_SECONDS:-60}
if [ "$fuzz_seconds" != 0 ]; then
  bash "$root/scripts/fuzz.sh" "$fuzz_seconds" || status=$?
fi
exit "$status"

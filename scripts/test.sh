#!/usr/bin/env bash
# One command for the whole test suite: install what is missing, build, run ctest.
set -euo pipefail
root=$(cd "$(dirname "$0")/.." && pwd)
bash "$root/scripts/setup.sh"
bash "$root/scripts/build.sh"
cd "${GAPS_BUILD_DIR:-$root/build}"
ctest --output-on-failure -j "${GAPS_TEST_JOBS:-2}" "$@"

#!/usr/bin/env bash
# One command for a newcomer: install what is missing, build, run `gaps demo`.
set -euo pipefail
root=$(cd "$(dirname "$0")/.." && pwd)
bash "$root/scripts/setup.sh"
bash "$root/scripts/build.sh"
exec "${GAPS_BUILD_DIR:-$root/build}/client/gaps" demo "$@"

#!/usr/bin/env bash
# One command for a newcomer: install what is missing, build, run `gaps demo`.
set -euo pipefail
root=$(cd "$(dirname "$0")/.." && pwd)
bash "$root/scripts/setup.sh"
bash "$root/scripts/build.sh"
# The demo reuses its folder: --overwrite replaces the previous demo's results.
exec "${GAPS_BUILD_DIR:-$root/build}/client/gaps" demo --overwrite "$@"

#!/usr/bin/env bash
# GAPS' machinery against the method before it, w/o GAPS and vanilla (configs/gaps_machinery.json), through
# run_matrix.sh (which says what the environment sets). Every cell but bonsai 24's full_paper_nthr, which equals
# its full cell, unless ONLY says otherwise.
#
#   bench/gaps_machinery.sh DATA OUT [GPUS]     e.g. bench/gaps_machinery.sh ../shared/data runs/machinery 0,1,2,3
set -euo pipefail
here=$(cd "$(dirname "$0")" && pwd)
ONLY=${ONLY:-^(?!bonsai_v24_full_paper_nthr)} exec bash "$here/run_matrix.sh" "$here/configs/gaps_machinery.json" "$@"

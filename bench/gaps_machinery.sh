#!/usr/bin/env bash
# GAPS' machinery against the method before it, w/o GAPS and vanilla (configs/gaps_machinery.json): the five
# initialisations first (init_settings.sh), then every cell at once, spread over the GPUs, with PSNR, SSIM
# and LPIPS-VGG. Resumable: finished cells are skipped on a second run.
#
#   bench/gaps_machinery.sh DATA OUT [GPUS]     e.g. bench/gaps_machinery.sh ../shared/data runs/machinery 0,1,2,3
# Environment: GAPS (default build/client/gaps), JOBS (cells at once, default 72: all), LPIPS_WEIGHTS (default:
# the set-up's file), GAPS_COMMIT (read by harness.py: the commit the rows name, for a copy of the tree without .git), ONLY (a regular expression on cell names; default: every cell but bonsai 24's
# full_paper_nthr, which equals its full cell). Writes OUT/results.jsonl (bench/tables.py reads it).
set -euo pipefail
here=$(cd "$(dirname "$0")" && pwd)
data=${1:?data root (e.g. ../shared/data)}
out=${2:?output folder}
gpus=${3:-0}
gaps=${GAPS:-$here/../build/client/gaps}
only=${ONLY:-^(?!bonsai_v24_full_paper_nthr)}
flags=(--flag device=cuda)
[ -n "${LPIPS_WEIGHTS:-}" ] && flags+=(--flag "lpips-weights=$LPIPS_WEIGHTS")
echo "gaps_machinery: initialising the five settings"
bash "$here/init_settings.sh" "$gaps" "$data" "$out" ""
echo "gaps_machinery: training"
python3 "$here/harness.py" --config "$here/configs/gaps_machinery.json" --data "$data" --out "$out/cells" \
  --gaps "$gaps" --gpus "$gpus" --jobs "${JOBS:-72}" "${flags[@]}" --only "$only"

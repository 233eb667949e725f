#!/usr/bin/env bash
# A benchmark matrix (a harness config of bench/configs/) on CUDA with PSNR, SSIM and LPIPS-VGG: the settings'
# initialisations first (init_settings.sh, into the init cache its cells then read), then every cell at once,
# spread over the GPUs. Resumable: finished cells are skipped on a second run.
#
#   bench/run_matrix.sh CONFIG DATA OUT [GPUS]     e.g. bench/run_matrix.sh bench/configs/restore_training.json ../shared/data runs/restore 0,1
# Environment: GAPS (default build/client/gaps), JOBS (cells at once, default 72), LPIPS_WEIGHTS (default: the
# set-up's file), GAPS_COMMIT (read by harness.py: the commit the rows name, for a copy of the tree without .git),
# ONLY (a Python regular expression on cell names "<scene>_v<views>_<arm>_s<seed>"), INIT_ONLY (a bash regular
# expression on "<scene>_v<views>_": the initialisations made first; default all five).
# Writes OUT/results.jsonl (bench/tables.py reads it).
set -euo pipefail
here=$(cd "$(dirname "$0")" && pwd)
config=${1:?harness config (bench/configs/*.json)}
data=${2:?data root (e.g. ../shared/data)}
out=${3:?output folder}
gpus=${4:-0}
gaps=${GAPS:-$here/../build/client/gaps}
only=${ONLY:-}
flags=(--flag device=cuda)
[ -n "${LPIPS_WEIGHTS:-}" ] && flags+=(--flag "lpips-weights=$LPIPS_WEIGHTS")
name=$(basename "$config" .json)
echo "$name: initialising the settings"
bash "$here/init_settings.sh" "$gaps" "$data" "$out" "${INIT_ONLY:-}"
echo "$name: training"
python3 "$here/harness.py" --config "$config" --data "$data" --out "$out/cells" \
  --gaps "$gaps" --gpus "$gpus" --jobs "${JOBS:-72}" "${flags[@]}" --only "$only"

#!/usr/bin/env bash
# The generator evaluation (generator_eval_bench) of the five benchmark settings (fern 3/6/9, bonsai 12/24; -r 8,
# init auto, vanilla to 10,000 iterations, backends asked at 1,000, 5,000 and 9,500) on CUDA, all settings at once,
# every arm of configs/generator_eval.json; the rows of all settings into one file, comparison strips per setting.
#
#   bench/generator_eval.sh DATA OUT.jsonl [IMAGES_DIR]
# Environment: BENCH (the benchmark binary, default build/bench/generator_eval_bench), DEVICE (default cuda),
# GAPS_CACHE (the set-up's cache: Real-ESRGAN and LPIPS weights, the init cache), EXTRA (more flags for every
# setting, e.g. "--arms render,reproject"), SETTINGS (the settings to run, "SCENE:VIEWS[:ITERATIONS]" separated by
# spaces, default all five at 1000,5000,9500; e.g. "llff/fern:6:9500" completes a setting measured in part).
set -euo pipefail
here=$(cd "$(dirname "$0")" && pwd)
data=${1:?data root (e.g. ../shared/data)}
out=${2:?output .jsonl}
images=${3:-}
bench=${BENCH:-$here/../build/bench/generator_eval_bench}
work=$(mktemp -d)
pids=()
for setting in ${SETTINGS:-llff/fern:3 llff/fern:6 llff/fern:9 mipnerf360/bonsai:12 mipnerf360/bonsai:24}; do
  IFS=: read -r scene views iterations <<<"$setting"
  name=$(basename "$scene")_$views
  args=(--scene "$data/$scene" --views "$views" --device "${DEVICE:-cuda}" --out "$work/$name.jsonl")
  [ -n "$iterations" ] && args+=(--iterations "$iterations")
  [ -n "$images" ] && args+=(--images "$images/$name")
  # shellcheck disable=SC2086
  "$bench" "${args[@]}" ${EXTRA:-} >"$work/$name.log" 2>&1 &
  pids+=($!)
done
status=0
for pid in "${pids[@]}"; do wait "$pid" || status=1; done
for log in "$work"/*.log; do
  grep -q '"bench":"generator_eval"' "$log" || { echo "$(basename "$log" .log):"; tail -5 "$log"; }
done
# Every row names the commit (GAPS_COMMIT for a copy of the tree without .git) and the machine.
commit=${GAPS_COMMIT:-$(git -C "$here" rev-parse --short HEAD 2>/dev/null || echo unknown)}
machine=$( (nvidia-smi --query-gpu=name --format=csv,noheader 2>/dev/null | head -1) || true)
[ -n "$machine" ] || machine=$(grep -m1 'model name' /proc/cpuinfo | cut -d: -f2- | sed 's/^ //')
machine="$machine ($(nproc) threads)"
cat "$work"/*.jsonl 2>/dev/null | COMMIT=$commit MACHINE=$machine python3 -c '
import json, os, sys
for line in sys.stdin:
    row = json.loads(line)
    row.update(commit=os.environ["COMMIT"], machine=os.environ["MACHINE"])
    print(json.dumps(row))' >>"$out"
echo "generator_eval: $(cat "$work"/*.jsonl 2>/dev/null | wc -l) rows appended to $out"
exit $status

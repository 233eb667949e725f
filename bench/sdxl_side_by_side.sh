#!/usr/bin/env bash
# SDXL speed, LibTorch (bench/sdxl_bench.cpp) vs diffusers (bench/sdxl_diffusers_bench.py), on the same GPU
# and the same random full-size weights, one after the other in one run. Needs a CUDA build of gaps
# (build/bench/sdxl_bench) and diffusers/transformers/accelerate in the Python environment.
#   bash bench/sdxl_side_by_side.sh [MODEL_DIR] [OUT.jsonl]   (GAPS_BUILD: the build folder, default build/)
set -euo pipefail
root=$(cd "$(dirname "$0")/.." && pwd)
model=${1:-/tmp/gaps_sdxl_random}
out=${2:-$root/bench/results/sdxl_gpu_$(date -u +%Y-%m-%d).jsonl}
python=${GAPS_PYTHON:-$HOME/.cache/gaps/venv/bin/python}
"${GAPS_BUILD:-$root/build}/bench/sdxl_bench" --model_dir "$model" --write_model --json "$out"
"$python" "$root/bench/sdxl_diffusers_bench.py" --model_dir "$model" --json "$out"
echo "results: $out"

#!/usr/bin/env bash
# The sdxl backend's models, LibTorch (bench/generator_bench.cpp) vs diffusers (bench/generator_diffusers_bench.py),
# on the same GPU and the same random full-size weights, in one run: the SDXL folder (generator_bench
# --write_model), the other components (bench/make_random_generator_weights.py), then both benchmarks. Folders
# that are already complete are reused. Needs a CUDA build of gaps (build/bench/generator_bench) and
# diffusers/transformers/accelerate (peft for diffusers' LoRA cases) in the Python environment.
#   bash bench/generator_side_by_side.sh [WORK_DIR] [OUT.jsonl]
#   (GAPS_BUILD: the build folder, default build/; GAPS_PYTHON: the Python, default the project's venv;
#    extra arguments for both benchmarks in GAPS_BENCH_ARGS, e.g. "--runs 5"; GAPS_TINY=1: the tiny test
#    SDXL's configs and tiny components, for a CPU smoke test with
#    GAPS_BENCH_ARGS="--device cpu --dtype float32 --sizes 32x24 --steps 4 --inpaint_steps 2 --runs 1")
set -euo pipefail
root=$(cd "$(dirname "$0")/.." && pwd)
work=${1:-/tmp/gaps_generator_bench}
out=${2:-$root/bench/results/generator_gpu_$(date -u +%Y-%m-%d).jsonl}
python=${GAPS_PYTHON:-$HOME/.cache/gaps/venv/bin/python}
bench="${GAPS_BUILD:-$root/build}/bench/generator_bench"
commit=${GAPS_COMMIT:-$(git -C "$root" rev-parse --short HEAD 2>/dev/null || echo unknown)}
extra=(${GAPS_BENCH_ARGS:-})
sdxl_args=() weights_args=()
if [ "${GAPS_TINY:-0}" = 1 ]; then
  sdxl_args=(--configs_from "$root/tests/fixtures/sdxl_tiny/model" --lora_size 32x24)
  weights_args=(--tiny)
fi
mkdir -p "$work" "$(dirname "$out")"
"$bench" --sdxl_dir "$work/sdxl" --write_model --write_only "${sdxl_args[@]}"
"$python" "$root/bench/make_random_generator_weights.py" --sdxl_dir "$work/sdxl" --out "$work/components" \
  "${weights_args[@]}"
"$bench" --sdxl_dir "$work/sdxl" --weights_dir "$work/components" --commit "$commit" --json "$out" \
  "${sdxl_args[@]}" "${extra[@]}"
"$python" "$root/bench/generator_diffusers_bench.py" --sdxl_dir "$work/sdxl" --weights_dir "$work/components" \
  --commit "$commit" --json "$out" "${extra[@]}"
echo "results: $out"

#!/usr/bin/env bash
# Vanilla 3DGS against the paper's method on LLFF fern, 10,000 iterations per run, one JSON line per run
# (metrics.json fields plus process wall time and peak GPU memory from nvidia-smi when present).
#   bench/fern_variants.sh BUILD_DIR DATA_DIR OUT_DIR DEVICE [VIEWS:VARIANT ...]
#   e.g. bench/fern_variants.sh build ../shared/data out/fern cuda 3:vanilla 3:full
set -euo pipefail
build=$1 data=$2 out=$3 device=$4
shift 4
mkdir -p "$out"
for spec in "$@"; do
  views=${spec%%:*} variant=${spec##*:}
  name=fern${views}_${variant}
  mon=""
  if command -v nvidia-smi > /dev/null; then
    nvidia-smi --query-gpu=memory.used --format=csv,noheader,nounits -lms 100 > "$out/$name.mem" &
    mon=$!
  fi
  start=$(date +%s.%N)
  "$build/client/gaps" train --scene "$data/llff/fern" --views "$views" --resolution 8 --iterations 10000 \
    --seed 0 --device "$device" --variant "$variant" --out "$out/$name" --quiet
  end=$(date +%s.%N)
  peak=null
  if [ -n "$mon" ]; then kill "$mon"; peak=$(sort -n "$out/$name.mem" | tail -1); fi
  python3 -c 'import json,sys; m=json.load(open(sys.argv[1])); m.pop("per_view",None); m["wall_seconds_process"]=float(sys.argv[3])-float(sys.argv[2]); m["gpu_memory_used_peak_mib"]=json.loads(sys.argv[4]); print(json.dumps(m))' \
    "$out/$name/metrics.json" "$start" "$end" "$peak" | tee -a "$out/results.jsonl"
done

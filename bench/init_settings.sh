#!/usr/bin/env bash
# The initialisations of the five benchmark settings (fern 3/6/9, bonsai 12/24; -r 8, --init auto, CUDA), all
# at once, into the init cache that the matrix's cells then read instead of each computing its own at the
# same time. Used by paper_tables.sh and gaps_machinery.sh.
#
#   bench/init_settings.sh GAPS DATA OUT [ONLY]    ONLY: a regular expression on "<scene>_v<views>_"
# Writes OUT/init/<scene>_<views>/ and its log beside it.
set -uo pipefail
gaps=${1:?gaps binary}
data=${2:?data root}
out=${3:?output folder}
only=${4:-}
mkdir -p "$out/init"
pids=()
for setting in llff/fern:3 llff/fern:6 llff/fern:9 mipnerf360/bonsai:12 mipnerf360/bonsai:24; do
  scene=${setting%%:*} views=${setting##*:}
  name=$(basename "$scene")_$views
  [[ "$(basename "$scene")_v${views}_" =~ $only ]] || continue
  "$gaps" init --scene "$data/$scene" --views "$views" -r 8 --init auto --device cuda --overwrite \
    --out "$out/init/$name" >"$out/init/$name.log" 2>&1 &
  pids+=($!)
done
for pid in "${pids[@]}"; do wait "$pid"; done

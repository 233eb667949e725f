#!/usr/bin/env bash
# The paper's tables (configs/paper_tables.json) and its ablation (configs/paper_ablation.json) in one go, with
# PSNR, SSIM and LPIPS-VGG: the five initialisations first (one per scene and view count, into the init cache
# that every cell then reads instead of computing its own at the same time), then every cell at once, spread
# over the GPUs. The ablation's vanilla and full cells are the tables' (same flags): they are trained once and
# their rows are copied into the ablation's results under its config name.
#
#   bench/paper_tables.sh DATA OUT [GPUS]     e.g. bench/paper_tables.sh ../shared/data runs/paper 0,1,2,3
# Environment: GAPS (the gaps binary, default build/client/gaps), JOBS (cells at once, default 42: all),
# GAPS_COMMIT (the commit the rows name, for a copy of the tree whose .git is not its own), LPIPS_WEIGHTS
# (default: the set-up's file), ONLY (a regular expression on cell names, e.g. ^fern_: only those
# cells and their scenes' initialisations). Resumable: finished cells are skipped on a second run.
# Writes OUT/tables/results.jsonl and OUT/ablation/results.jsonl (bench/tables.py and bench/charts.py read them).
set -euo pipefail
here=$(cd "$(dirname "$0")" && pwd)
data=${1:?data root (e.g. ../shared/data)}
out=${2:?output folder}
gpus=${3:-0}
gaps=${GAPS:-$here/../build/client/gaps}
jobs=${JOBS:-42}
only=${ONLY:-}
flags=(--flag device=cuda)
[ -n "${LPIPS_WEIGHTS:-}" ] && flags+=(--flag "lpips-weights=$LPIPS_WEIGHTS")

echo "paper_tables: initialising the five settings"
bash "$here/init_settings.sh" "$gaps" "$data" "$out" "$only"

echo "paper_tables: training"
python3 "$here/harness.py" --config "$here/configs/paper_tables.json" --data "$data" --out "$out/tables" \
  --gaps "$gaps" --gpus "$gpus" --jobs "$((jobs * 30 / 42 > 0 ? jobs * 30 / 42 : 1))" "${flags[@]}" --only "$only" &
tables=$!
python3 "$here/harness.py" --config "$here/configs/paper_ablation.json" --data "$data" --out "$out/ablation" \
  --gaps "$gaps" --gpus "$gpus" --jobs "$((jobs * 12 / 42 > 0 ? jobs * 12 / 42 : 1))" "${flags[@]}" \
  --only "$only.*_(no-gaps|no-dropgaussian)_" &
ablation=$!
status=0
wait "$tables" || status=$?
wait "$ablation" || status=$?

# The shared cells, under the ablation's name, beside its own rows.
python3 - "$out" <<'EOF'
import json, sys
from pathlib import Path
out = Path(sys.argv[1])
shared = [json.loads(l) for l in (out / "tables" / "results.jsonl").read_text().splitlines() if l.strip()]
own = [json.loads(l) for l in (out / "ablation" / "results.jsonl").read_text().splitlines() if l.strip()]
settings = {("fern", 3), ("bonsai", 24)}
copied = [dict(r, config="paper_ablation") for r in shared
          if (r["scene"], r["views"]) in settings and r["variant"] in ("vanilla", "full")]
with open(out / "ablation" / "results_with_shared.jsonl", "w") as f:
    for r in own + copied:
        f.write(json.dumps(r) + "\n")
print(f"paper_tables: ablation rows: {len(own)} own + {len(copied)} shared")
EOF
exit "$status"

#!/usr/bin/env python3
"""What a finished run's diffusion phases did, from its output folder's phases.json (and metrics.json): the
sections' and generator stages' seconds summed over the phases, the generator's counters, admissions, and the
img2img strengths the requests asked for. One JSON line, as the rows of placements_bench.py and
service_overhead.py carry it.

  python3 bench/phase_summary.py runs/fern [--steps 30]
(--steps: the generator's schedule length, for a histogram of the denoising steps int(steps x strength).)
"""
import argparse
import collections
import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from placements_bench import phase_breakdown  # noqa: E402


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("run", type=Path, help="a run's output folder (gaps train --out, or a fetched job)")
    ap.add_argument("--steps", type=int, default=30, help="the generator's schedule length")
    args = ap.parse_args()
    phases_file = args.run / "phases.json"
    if not phases_file.exists():
        sys.exit(f"phase_summary: {phases_file} does not exist (a vanilla run, or not finished)")
    phases = json.loads(phases_file.read_text())
    steps = collections.Counter(int(args.steps * s["strength"]) for p in phases for s in p.get("selection", [])
                                if "strength" in s)
    metrics_file = args.run / "metrics.json"
    metrics = json.loads(metrics_file.read_text()) if metrics_file.exists() else {}
    print(json.dumps({"run": str(args.run), "psnr": metrics.get("psnr"), "lpips": metrics.get("lpips"),
                      "train_seconds": metrics.get("train_seconds"), **phase_breakdown(phases),
                      "denoising_steps": {str(k): v for k, v in sorted(steps.items())}}))


if __name__ == "__main__":
    main()

#!/usr/bin/env python3
"""Markdown tables from generator_eval_bench's rows (bench/generator_eval.sh): per setting and iteration every arm's
PSNR / SSIM / LPIPS against the held-out photographs with the difference to the plain render, and how many of its
views the admission gate took; then, pooled over settings and iterations, each arm's per-view difference to the
render by the test pose's distance to the nearest training camera. Standard library only.

  bench/generator_eval_tables.py bench/results/generator_eval_*.jsonl [--insert docs/benchmarks.md]
The markers:  <!-- bench-tables:generator_eval begin -->  ...  <!-- bench-tables:generator_eval end -->
"""
import argparse
import json
import statistics
import sys
from collections import defaultdict

import tables

BASELINE = "render"
DISTANCE_BINS = [(0.0, 1.0, "< 1"), (1.0, 2.0, "1–2"), (2.0, float("inf"), "≥ 2")]


def load_rows(paths):
    rows = []
    for path in paths:
        with open(path) as f:
            rows += [json.loads(line) for line in f if line.strip()]
    return rows


def num(value, digits, signed=False):
    if value is None:
        return "–"
    return f"{value:+.{digits}f}" if signed else f"{value:.{digits}f}"


def setting_key(row):
    return (row["scene"], row["views"])


def arm_table(rows):
    """One line per setting, iteration and arm, the render's first; differences to the render of the same cell."""
    cells = defaultdict(dict)
    for r in rows:
        cells[(setting_key(r), r["iteration"])][r["arm"]] = r
    out = ["| setting | iteration | arm | PSNR | Δ | SSIM | LPIPS | Δ | admitted |",
           "|---|---:|---|---:|---:|---:|---:|---:|---:|"]
    for (setting, iteration), arms in sorted(cells.items()):
        base = arms.get(BASELINE)
        for name, r in sorted(arms.items(), key=lambda kv: (kv[0] != BASELINE, list(arms).index(kv[0]))):
            d_psnr = r["psnr"] - base["psnr"] if base and name != BASELINE else None
            d_lpips = (r["lpips"] - base["lpips"] if base and name != BASELINE and r["lpips"] is not None
                       and base["lpips"] is not None else None)
            admitted = "–" if r["admitted"] is None else f"{r['admitted']}/{r['test_views']}"
            out.append(f"| {setting[0]} {setting[1]} | {iteration} | {name} | {num(r['psnr'], 2)} | "
                       f"{num(d_psnr, 2, True)} | {num(r['ssim'], 3)} | {num(r['lpips'], 3)} | "
                       f"{num(d_lpips, 3, True)} | {admitted} |")
    return "\n".join(out)


def distance_table(rows):
    """Per arm and distance bin: the mean per-view ΔPSNR and ΔLPIPS to the render at the same view, and views."""
    base = {(setting_key(r), r["iteration"], v["view"]): v
            for r in rows if r["arm"] == BASELINE for v in r["per_view"]}
    pooled = defaultdict(lambda: defaultdict(list))
    arms = []
    for r in rows:
        if r["arm"] == BASELINE:
            continue
        arms += [r["arm"]] if r["arm"] not in arms else []
        for v in r["per_view"]:
            b = base.get((setting_key(r), r["iteration"], v["view"]))
            if b is None:
                continue
            for low, high, label in DISTANCE_BINS:
                if low <= v["pose_distance"] < high:
                    lpips = v["lpips"] - b["lpips"] if v["lpips"] is not None and b["lpips"] is not None else None
                    pooled[r["arm"]][label].append((v["psnr"] - b["psnr"], lpips, v.get("admitted")))
    labels = [label for _, _, label in DISTANCE_BINS]
    out = ["| arm | " + " | ".join(f"{label} baselines: ΔPSNR / ΔLPIPS (views, admitted)" for label in labels) + " |",
           "|---|" + "---:|" * len(labels)]
    for arm in arms:
        cols = []
        for label in labels:
            views = pooled[arm][label]
            if not views:
                cols.append("–")
                continue
            d_psnr = statistics.mean(p for p, _, _ in views)
            lp = [l for _, l, _ in views if l is not None]
            admitted = sum(1 for _, _, a in views if a)
            cols.append(f"{d_psnr:+.2f} / {num(statistics.mean(lp) if lp else None, 3, True)} "
                        f"({len(views)}, {admitted})")
        out.append(f"| {arm} | " + " | ".join(cols) + " |")
    return "\n".join(out)


def render_all(rows):
    commits = sorted({r.get("commit", "?") for r in rows})
    machines = sorted({r.get("machine", "?") for r in rows})
    return (f"Rows: {len(rows)}; commit {', '.join(commits)}; {', '.join(machines)}.\n\n" + arm_table(rows) +
            "\n\nPer view, pooled over the settings and iterations above, by the test pose's distance to the nearest "
            "training camera (in training-camera spacings):\n\n" + distance_table(rows) + "\n")


def insert(document, text):
    """tables.insert for the generator_eval markers; a document without them is an error that names them."""
    try:
        return tables.insert(document, {"generator_eval": text})
    except KeyError as e:
        raise SystemExit(e.args[0])


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("results", nargs="+", help="rows of generator_eval_bench")
    parser.add_argument("--insert", help="markdown file to update between its generator_eval markers")
    args = parser.parse_args(argv)
    text = render_all(load_rows(args.results))
    if not args.insert:
        sys.stdout.write(text)
        return 0
    with open(args.insert) as f:
        document = f.read()
    with open(args.insert, "w") as f:
        f.write(insert(document, text))
    return 0


if __name__ == "__main__":
    sys.exit(main())

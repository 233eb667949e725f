#!/usr/bin/env python3
"""Markdown tables in the paper's format from the harness's rows (results.jsonl).

Per benchmark config: average PSNR / SSIM / LPIPS per view count and variant (mean ± std over seeds, the
scene average taken per seed), their difference to vanilla, per-scene PSNR with the difference to vanilla,
and the cost of each setting (Gaussians, peak memory, training and generator seconds). Standard library only.

  bench/tables.py runs/llff/results.jsonl [more.jsonl ...]                   # print
  bench/tables.py runs/*/results.jsonl --insert docs/benchmarks.md          # replace between markers
The markers, one pair per config:  <!-- bench-tables:CONFIG begin -->  ...  <!-- bench-tables:CONFIG end -->
"""
import argparse
import json
import math
import re
import statistics
import sys
from collections import defaultdict

VANILLA = "vanilla"
VARIANT_ORDER = ["vanilla", "no-gaps", "no-dropgaussian", "full"]


def load_rows(paths):
    rows = []
    for path in paths:
        with open(path) as f:
            rows += [json.loads(line) for line in f if line.strip()]
    # A cell run twice (e.g. results of two output folders merged) counts once: the last row wins.
    unique = {}
    for row in rows:
        unique[(row["config"], row["cell"])] = row
    return list(unique.values())


def variant_key(variant):
    return (VARIANT_ORDER.index(variant) if variant in VARIANT_ORDER else len(VARIANT_ORDER), variant)


def mean_std(values):
    """(mean, sample std or None for a single value); None for no values or any missing value."""
    if not values or any(v is None for v in values):
        return None
    return statistics.fmean(values), (statistics.stdev(values) if len(values) > 1 else None)


def fmt(stat, digits):
    if stat is None:
        return "n/a"
    mean, std = stat
    return f"{mean:.{digits}f}" if std is None else f"{mean:.{digits}f} ± {std:.{digits}f}"


def fmt_delta(value, digits):
    return "n/a" if value is None else f"{value:+.{digits}f}"


def seed_averages(rows, metric, scenes):
    """Per seed, the metric averaged over `scenes` (seeds lacking a scene are left out)."""
    by_seed = defaultdict(dict)
    for r in rows:
        by_seed[r["seed"]][r["scene"]] = r.get(metric)
    out = []
    for seed in sorted(by_seed):
        values = by_seed[seed]
        if set(values) >= set(scenes):
            vs = [values[s] for s in scenes]
            out.append(None if any(v is None for v in vs) else statistics.fmean(vs))
    return out


METRICS = [("psnr", "PSNR↑", 2), ("ssim", "SSIM↑", 4), ("lpips", "LPIPS↓", 4)]


def scenes_at(rows, views):
    """The scenes run at this view count: a config may mix datasets of different view counts (LLFF 3/6/9,
    Mip-NeRF 360 12/24), and the paper averages each view count over the scenes that have it."""
    return sorted({r["scene"] for r in rows if r["views"] == views})


def averages_table(rows, views_list, variants):
    header = "| variant | " + " | ".join(f"{name} ({v} views)" for v in views_list for _, name, _ in METRICS) + " |"
    lines = [header, "|---" * (1 + len(views_list) * len(METRICS)) + "|"]
    means = {}
    for variant in variants:
        cells = []
        for views in views_list:
            subset = [r for r in rows if r["variant"] == variant and r["views"] == views]
            for metric, _, digits in METRICS:
                stat = mean_std(seed_averages(subset, metric, scenes_at(rows, views)))
                means[(variant, views, metric)] = stat[0] if stat else None
                cells.append(fmt(stat, digits))
        lines.append(f"| {variant} | " + " | ".join(cells) + " |")
    for variant in variants:
        if variant == VANILLA or VANILLA not in variants:
            continue
        cells = []
        for views in views_list:
            for metric, _, digits in METRICS:
                a, b = means.get((variant, views, metric)), means.get((VANILLA, views, metric))
                cells.append(fmt_delta(None if a is None or b is None else a - b, digits))
        lines.append(f"| Δ {variant} − vanilla | " + " | ".join(cells) + " |")
    return lines


def per_scene_table(rows, scenes, views_list, variants):
    lines = ["| scene | variant | " + " | ".join(f"PSNR ({v} views)" for v in views_list) + " |",
             "|---|---" + "|---" * len(views_list) + "|"]
    for scene in scenes:
        for variant in variants:
            cells = []
            for views in views_list:
                values = [r["psnr"] for r in rows if (r["scene"], r["variant"], r["views"]) == (scene, variant, views)]
                stat = mean_std(values)
                text = fmt(stat, 2)
                if variant != VANILLA and stat is not None:
                    base = mean_std([r["psnr"] for r in rows
                                     if (r["scene"], r["variant"], r["views"]) == (scene, VANILLA, views)])
                    if base is not None:
                        text += f" ({stat[0] - base[0]:+.2f})"
                cells.append(text)
            lines.append(f"| {scene} | {variant} | " + " | ".join(cells) + " |")
    return lines


def cost_table(rows, views_list, variants):
    lines = ["| views | variant | runs | Gaussians | peak memory MiB | training s | generator s | device |",
             "|---|---|---|---|---|---|---|---|"]
    for views in views_list:
        for variant in variants:
            subset = [r for r in rows if r["variant"] == variant and r["views"] == views]
            if not subset:
                continue
            mib = [None if r.get("peak_memory_bytes") is None else r["peak_memory_bytes"] / 2**20 for r in subset]
            kinds = sorted({str(r.get("peak_memory_kind")) for r in subset})
            devices = sorted({str(r.get("device")) for r in subset})
            lines.append(f"| {views} | {variant} | {len(subset)} | {fmt(mean_std([r['num_gaussians'] for r in subset]), 0)}"
                         f" | {fmt(mean_std(mib), 0)} ({', '.join(kinds)}) | {fmt(mean_std([r['train_seconds'] for r in subset]), 1)}"
                         f" | {fmt(mean_std([r.get('generator_seconds') for r in subset]), 1)} | {'; '.join(devices)} |")
    return lines


def config_tables(config, rows):
    finished = [r for r in rows if r.get("status", "ok") == "ok"]
    failed = [r for r in rows if r.get("status", "ok") != "ok"]
    scenes = sorted({r["scene"] for r in finished})
    views_list = sorted({r["views"] for r in finished})
    variants = sorted({r["variant"] for r in finished}, key=variant_key)
    seeds = sorted({r["seed"] for r in finished})
    commits = sorted({str(r.get("commit")) for r in rows})
    out = [f"Generated by `bench/tables.py` from {len(rows)} runs of `{config}` (scenes {', '.join(scenes)}; "
           f"seeds {', '.join(map(str, seeds))}; commit {', '.join(commits)}). Mean ± sample std over seeds; "
           "scene averages are taken per seed over the scenes run at that view count. LPIPS is n/a where the runs had no VGG16 backbone.", ""]
    if failed:
        out += [f"Runs that did not finish ({len(failed)}), left out of the tables: " +
                "; ".join(f"{r['cell']}: {r.get('status')} ({r.get('error') or 'no message'})" for r in failed), ""]
    if finished:
        out += ["Average over scenes:", ""] + averages_table(finished, views_list, variants)
        out += ["", "Per-scene PSNR (difference to vanilla in brackets):", ""] + per_scene_table(finished, scenes, views_list, variants)
        out += ["", "Cost per run:", ""] + cost_table(finished, views_list, variants)
    return "\n".join(out) + "\n"


def render_all(rows):
    by_config = defaultdict(list)
    for r in rows:
        by_config[r["config"]].append(r)
    return {config: config_tables(config, by_config[config]) for config in sorted(by_config)}


def insert(document, tables):
    """Replaces the text between each config's markers; a config without markers is an error."""
    for config, text in tables.items():
        begin, end = f"<!-- bench-tables:{config} begin -->", f"<!-- bench-tables:{config} end -->"
        pattern = re.compile(re.escape(begin) + r".*?" + re.escape(end), re.S)
        if not pattern.search(document):
            raise KeyError(f"no markers '{begin}' ... '{end}' in the document for config {config}")
        document = pattern.sub(lambda _: f"{begin}\n{text}{end}", document)
    return document


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("results", nargs="+", help="results.jsonl files written by bench/harness.py")
    parser.add_argument("--insert", help="markdown file to update between its bench-tables markers")
    args = parser.parse_args(argv)
    tables = render_all(load_rows(args.results))
    if not args.insert:
        for config, text in tables.items():
            print(f"### {config}\n\n{text}")
        return 0
    with open(args.insert) as f:
        document = f.read()
    try:
        document = insert(document, tables)
    except KeyError as e:
        print(f"tables.py: {e.args[0]}", file=sys.stderr)
        return 1
    with open(args.insert, "w") as f:
        f.write(document)
    print(f"updated {args.insert}: {', '.join(tables)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

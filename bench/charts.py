#!/usr/bin/env python3
"""Speed-vs-accuracy charts from the harness's rows (results.jsonl), as PNG and SVG (matplotlib, Agg).

Per config, scene and view count: test PSNR, and test LPIPS where the runs measured it, against wall-clock
training time, one line per run through the points of its evaluation curve, coloured by variant. Per config: final test PSNR against the number of
Gaussians, one point per run. Across configs, per scene and view count where runs under a Gaussian budget
exist: test PSNR against the model size, one line per method through its budgets (mean over seeds; the
hollow marker is unlimited growth). An index (README.md) in the output folder lists and captions every chart.

Given --speed-runs (standalone timing runs of successive commits, bench/results/train_speed_*.jsonl): per
machine, scene and view count, final test PSNR against training time, a line per variant through the commits.

  bench/charts.py runs/*/results.jsonl --out docs/charts [--formats png,svg] [--speed-runs FILE...]
"""
import argparse
import json
import os
import sys
from collections import defaultdict
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
import tables  # noqa: E402  (row loading and variant order are shared with the tables)

import matplotlib  # noqa: E402

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

COLOURS = {"vanilla": "#1f77b4", "full": "#d62728", "no-gaps": "#2ca02c", "no-dropgaussian": "#9467bd"}
MARKERS = ["o", "s", "^", "D", "v", "P"]
# Reproducible files: no timestamps, fixed SVG ids.
matplotlib.rcParams["svg.hashsalt"] = "gaps"
SAVE_METADATA = {"png": {"Software": None}, "svg": {"Date": None, "Creator": None}}


# Arms (a variant under its own label and flags) take the colours that no plain variant uses.
ARM_COLOURS = ["#ff7f0e", "#17becf", "#8c564b", "#e377c2", "#bcbd22", "#7f7f7f"]


def colour(variant):
    return COLOURS.get(variant, "#7f7f7f")


def label_colours(labels):
    """Colour per label: plain variants their own, arms one each from ARM_COLOURS in label order."""
    arms = sorted((l for l in labels if l not in COLOURS), key=tables.variant_key)
    out = {l: ARM_COLOURS[k % len(ARM_COLOURS)] for k, l in enumerate(arms)}
    out.update({l: COLOURS[l] for l in labels if l in COLOURS})
    return out


def save(fig, out, stem, formats):
    paths = []
    for fmt in formats:
        path = Path(out) / f"{stem}.{fmt}"
        fig.savefig(path, format=fmt, dpi=120, bbox_inches="tight", metadata=SAVE_METADATA.get(fmt))
        paths.append(path)
    plt.close(fig)
    return paths


# The metrics a curve chart can plot: y-axis label and name in titles and file names.
CURVE_METRICS = {"psnr": ("test PSNR, dB", "test PSNR"), "lpips": ("test LPIPS-VGG (lower is better)", "test LPIPS")}


def label_psnr_axes(ax, xlabel, heading, grid_which="major", ylabel=CURVE_METRICS["psnr"][0], **legend):
    """A chart's labels, heading, grid and legend (keyword arguments go to the legend); the y axis is test PSNR
    unless `ylabel` says otherwise."""
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    ax.set_title(heading)
    ax.grid(alpha=0.3, which=grid_which)
    ax.legend(**legend)


def metric_vs_time(config, scene, views, rows, out, formats, metric="psnr"):
    """`metric` (psnr or lpips) of every run's evaluation curve against its training time; nothing when no
    curve has the metric (LPIPS is null in runs without LPIPS weights)."""
    fig, ax = plt.subplots(figsize=(6.4, 4.2))
    colours = label_colours({r["variant"] for r in rows})
    labelled = set()
    for r in sorted(rows, key=lambda r: (tables.variant_key(r["variant"]), r["seed"])):
        curve = [p for p in r.get("curve") or [] if p.get(metric) is not None]
        if not curve:
            continue
        ax.plot([p["train_seconds"] for p in curve], [p[metric] for p in curve], marker="o", markersize=3,
                linewidth=1.2, alpha=0.85, color=colours[r["variant"]],
                label=None if r["variant"] in labelled else r["variant"])
        labelled.add(r["variant"])
    if not labelled:
        plt.close(fig)
        return []
    ylabel, name = CURVE_METRICS[metric]
    label_psnr_axes(ax, "training time, s (evaluations excluded)",
                    f"{scene}, {views} views: {name} over training time ({config})", ylabel=ylabel,
                    title="variant (one line per seed)")
    return save(fig, out, f"{config}_{scene}_v{views}_{metric}_vs_time", formats)


def psnr_vs_gaussians(config, rows, out, formats):
    finished = [r for r in rows if r.get("psnr") is not None and r.get("num_gaussians") is not None]
    if not finished:
        return []
    fig, ax = plt.subplots(figsize=(6.4, 4.2))
    settings = sorted({(r["scene"], r["views"]) for r in finished})
    colours = label_colours({r["variant"] for r in finished})
    for r in finished:
        ax.scatter(r["num_gaussians"], r["psnr"], color=colours[r["variant"]],
                   marker=MARKERS[settings.index((r["scene"], r["views"])) % len(MARKERS)], s=30, alpha=0.85)
    for variant in sorted({r["variant"] for r in finished}, key=tables.variant_key):
        ax.scatter([], [], color=colours[variant], marker="o", label=variant)
    for k, (scene, views) in enumerate(settings):
        ax.scatter([], [], color="#555", marker=MARKERS[k % len(MARKERS)], label=f"{scene}, {views} views")
    label_psnr_axes(ax, "Gaussians at the end of training", f"Test PSNR against model size ({config})", fontsize=8)
    return save(fig, out, f"{config}_psnr_vs_gaussians", formats)


def base_variant(label):
    """The method of a harness arm ("full_k2" -> "full"); plain variants are their own."""
    return label.split("_")[0]


def budgeted(r):
    return (r.get("max_gaussians") or 0) > 0


def initialisation(r):
    """The initialisation of a run: method and the resolution its images were read at (rows from before
    --init-resolution read the training resolution)."""
    return r.get("init"), r.get("init_resolution") or r.get("resolution")


def budget_points(rows):
    """Per method, (mean Gaussians, mean PSNR, budgeted) of each of its arms, sorted by size. Only runs from the
    budgeted runs' initialisation count: another initialisation is another experiment, not another budget."""
    inits = {initialisation(r) for r in rows if budgeted(r)}
    arms = defaultdict(list)
    for r in rows:
        if initialisation(r) in inits:
            arms[(base_variant(r["variant"]), r["variant"], budgeted(r))].append(r)
    points = defaultdict(list)
    for (method, _, is_budgeted), runs in arms.items():
        points[method].append((sum(r["num_gaussians"] for r in runs) / len(runs),
                               sum(r["psnr"] for r in runs) / len(runs), is_budgeted))
    return {method: sorted(p) for method, p in points.items()}


def psnr_vs_budget(scene, views, rows, out, formats):
    """One line per method through its budgets, or nothing when no run of this setting had a budget."""
    if not any(budgeted(r) for r in rows):
        return []
    fig, ax = plt.subplots(figsize=(6.4, 4.2))
    lines = budget_points(rows)
    for method in sorted(lines, key=tables.variant_key):
        points = lines[method]
        ax.plot([p[0] for p in points], [p[1] for p in points], color=colour(method), linewidth=1.2, label=method)
        for x, y, is_budgeted in points:
            ax.scatter(x, y, color=colour(method), facecolors=colour(method) if is_budgeted else "white", s=36, zorder=3)
    ax.set_xscale("log")
    label_psnr_axes(ax, "Gaussians at the end of training (log scale)",
                    f"{scene}, {views} views: test PSNR against the Gaussian budget", grid_which="both",
                    title="method (hollow: no budget)")
    return save(fig, out, f"budget_{scene}_v{views}_psnr_vs_gaussians", formats)


def machine_slug(machine):
    """'NVIDIA H100 80GB HBM3 (one card ...)' -> 'h100': the card's model for file names."""
    for word in machine.replace("(", " ").split():
        if word[:1] in "HABL" and any(c.isdigit() for c in word):
            return word.lower()
    return "gpu"


def speed_work(machine, scene, views, rows, out, formats):
    """Standalone runs of successive commits on one machine: final test PSNR against training time, a line per
    variant through the runs in their order, each point named by its run and commit."""
    fig, ax = plt.subplots(figsize=(6.4, 4.2))
    for variant in sorted({r["variant"] for r in rows}, key=tables.variant_key):
        points = [r for r in rows if r["variant"] == variant]
        xs, ys = [r["train_seconds"] for r in points], [r["psnr"] for r in points]
        ax.plot(xs, ys, linewidth=0.8, alpha=0.35, color=colour(variant))
        ax.scatter(xs, ys, s=18, color=colour(variant), label=variant, zorder=3)
        for r in points:
            ax.annotate(f"{str(r['run']).split()[0]} {r['build'][:7]}", (r["train_seconds"], r["psnr"]),
                        fontsize=6, xytext=(3, 3), textcoords="offset points")
    vanilla = sorted(r["train_seconds"] for r in rows if r["variant"] == tables.VANILLA)
    if vanilla:  # the speed goal of the method: at most 1.5 times vanilla's time
        ax.axvline(1.5 * vanilla[len(vanilla) // 2], color="#7f7f7f", linestyle=":", linewidth=1,
                   label="1.5 × vanilla's median time")
    name = Path(scene).name
    label_psnr_axes(ax, "training time, s (alone on the GPU)",
                    f"{name}, {views} views on {machine_slug(machine).upper()}: PSNR against time, per commit",
                    title="variant (runs in order)")
    return save(fig, out, f"speed_work_{machine_slug(machine)}_{name}_v{views}_psnr_vs_time", formats)


def render_speed_work(rows, out, formats):
    """The speed-work charts of standalone timing runs (rows with run, build, machine, scene, views, variant,
    train_seconds, psnr); one per machine, scene and view count. Returns [(caption, [paths])]."""
    Path(out).mkdir(parents=True, exist_ok=True)
    finished = [r for r in rows if r.get("rc", 0) == 0 and r.get("psnr") is not None and r.get("train_seconds")]
    written = []
    for machine, scene, views in sorted({(r["machine"], r["scene"], r["views"]) for r in finished}):
        subset = [r for r in finished if (r["machine"], r["scene"], r["views"]) == (machine, scene, views)]
        paths = speed_work(machine, scene, views, subset, out, formats)
        written.append((f"speed work on {machine.split(' (')[0]}: {Path(scene).name}, {views} views — final test "
                        "PSNR against training time, per commit", paths))
    return written


def render_all(rows, out, formats):
    """Every chart of `rows`; returns [(caption, [paths])]."""
    Path(out).mkdir(parents=True, exist_ok=True)
    written = []
    by_config = defaultdict(list)
    for r in rows:
        if r.get("status", "ok") == "ok":
            by_config[r["config"]].append(r)
    for config in sorted(by_config):
        rows_c = by_config[config]
        for scene, views in sorted({(r["scene"], r["views"]) for r in rows_c}):
            subset = [r for r in rows_c if (r["scene"], r["views"]) == (scene, views)]
            for metric, (_, name) in CURVE_METRICS.items():
                paths = metric_vs_time(config, scene, views, subset, out, formats, metric)
                if paths:
                    written.append((f"{config}: {scene}, {views} views — {name} over training time", paths))
        paths = psnr_vs_gaussians(config, rows_c, out, formats)
        if paths:
            written.append((f"{config}: test PSNR against the number of Gaussians", paths))
    finished = [r for rows_c in by_config.values() for r in rows_c if r.get("psnr") is not None]
    for scene, views in sorted({(r["scene"], r["views"]) for r in finished}):
        subset = [r for r in finished if (r["scene"], r["views"]) == (scene, views)]
        paths = psnr_vs_budget(scene, views, subset, out, formats)
        if paths:
            written.append((f"{scene}, {views} views — test PSNR against the Gaussian budget (all configs)", paths))
    return written


def write_index(out, written, sources):
    lines = ["# Charts", "", "Generated by `bench/charts.py` from " + ", ".join(f"`{s}`" for s in sources) +
             "; do not edit by hand.", ""]
    for caption, paths in written:
        first = paths[0].name
        lines += [f"## {caption}", "", f"![{caption}]({first})", ""]
        others = [p.name for p in paths[1:]]
        if others:
            lines += ["Also: " + ", ".join(f"[{n}]({n})" for n in others), ""]
    (Path(out) / "README.md").write_text("\n".join(lines))


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("results", nargs="+", help="results.jsonl files written by bench/harness.py")
    parser.add_argument("--out", default="docs/charts", help="output folder")
    parser.add_argument("--formats", default="png,svg", help="comma-separated: png, svg, pdf")
    parser.add_argument("--speed-runs", nargs="*", default=[],
                        help="JSON-lines files of standalone timing runs per commit (bench/results/train_speed_*)")
    args = parser.parse_args(argv)
    formats = [f.strip() for f in args.formats.split(",") if f.strip()]
    written = render_all(tables.load_rows(args.results), args.out, formats)
    if not written:
        print("charts.py: no finished runs with results in " + ", ".join(args.results), file=sys.stderr)
        return 1
    speed_rows = []
    for path in args.speed_runs:
        with open(path) as f:
            speed_rows += [json.loads(line) for line in f if line.strip()]
    written += render_speed_work(speed_rows, args.out, formats)
    write_index(args.out, written, [os.path.relpath(s) for s in args.results + args.speed_runs])
    for _, paths in written:
        for p in paths:
            print(p)
    return 0


if __name__ == "__main__":
    sys.exit(main())

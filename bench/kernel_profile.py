#!/usr/bin/env python3
"""Where a CUDA kernel of the rasterizer spends its time, per benchmark case, from Nsight Compute.

Runs `ncu` on rasterizer_speed_bench (or reads the CSV such a run wrote) and prints one JSON line per case (grid
size) with the median launch's duration, occupancy, issue rate, SM throughput, thread divergence and the rules
ncu fired with their estimated speedups. ncu locks the clocks to base, so its durations are for comparing builds
profiled the same way, not against the benchmark's milliseconds.

  python3 bench/kernel_profile.py --bench build-gpu/bench/rasterizer_speed_bench --kernel rasterize_backward_kernel \
      --csv_out ncu.csv --build COMMIT
  python3 bench/kernel_profile.py --csv ncu.csv --build COMMIT       # summarise an earlier run
"""
import argparse
import collections
import csv
import io
import json
import os
import shutil
import subprocess
import sys

SECTIONS = ["SpeedOfLight", "Occupancy", "SchedulerStats", "WarpStateStats", "MemoryWorkloadAnalysis"]
# rasterizer_speed_bench's cases by their grid of 16x16 tiles, two-dimensional or one block per tile in a row
# (100k and 300k share 504x378).
CASES = {"(32, 24, 1)": "100k and 300k at 504x378", "(768, 1, 1)": "100k and 300k at 504x378",
         "(63, 63, 1)": "1M at 1000x1000", "(3969, 1, 1)": "1M at 1000x1000"}
METRICS = {
    "Duration": "duration_ns",
    "Elapsed Cycles": "elapsed_cycles",
    "SM Active Cycles": "sm_active_cycles",
    "Compute (SM) Throughput": "sm_throughput_pct",
    "Issued Warp Per Scheduler": "issued_warp_per_scheduler",
    "Warp Cycles Per Issued Instruction": "warp_cycles_per_issued_instruction",
    "Avg. Active Threads Per Warp": "active_threads_per_warp",
    "Theoretical Occupancy": "theoretical_occupancy_pct",
    "Achieved Occupancy": "achieved_occupancy_pct",
    "Block Limit Registers": "block_limit_registers",
}


def run_ncu(bench, kernel, launches):
    ncu = shutil.which("ncu") or "/usr/local/cuda/bin/ncu"
    if not os.path.exists(ncu):
        sys.exit("kernel_profile: no ncu (Nsight Compute) on this machine")
    cmd = [ncu, "-k", f"regex:{kernel}", "-c", str(launches), "--csv", "--page", "details"]
    for s in SECTIONS:
        cmd += ["--section", s]
    cmd += [bench, "--runs", "2", "--cpu_runs", "0"]
    done = subprocess.run(cmd, capture_output=True, text=True)
    if done.returncode != 0:
        sys.exit(f"kernel_profile: ncu failed ({done.returncode}): {done.stderr[-2000:]}")
    return done.stdout


def number(text):
    try:
        return float(text.replace(",", ""))
    except ValueError:
        return None


def summarise(csv_text):
    rows = list(csv.DictReader(io.StringIO("".join(l for l in csv_text.splitlines(True) if l.startswith('"')))))
    if not rows:
        sys.exit("kernel_profile: no ncu rows in the CSV (did the kernel name match?)")
    launches = collections.OrderedDict()
    for r in rows:
        launch = launches.setdefault(r["ID"], {"grid": r["Grid Size"], "metrics": {}, "rules": {}})
        if r["Metric Name"] in METRICS:
            launch["metrics"][METRICS[r["Metric Name"]]] = number(r["Metric Value"])
        if r["Rule Name"] and number(r.get("Estimated Speedup", "")) is not None:
            launch["rules"][r["Rule Name"]] = number(r["Estimated Speedup"])
    by_grid = collections.OrderedDict()
    for launch in launches.values():
        by_grid.setdefault(launch["grid"], []).append(launch)
    for grid, group in by_grid.items():
        group.sort(key=lambda l: l["metrics"].get("duration_ns") or 0)
        median = group[len(group) // 2]
        yield {"grid": grid, "image": CASES.get(grid, "?"), "launches": len(group), **median["metrics"],
               "rules_estimated_speedup_pct": median["rules"]}


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--bench", help="rasterizer_speed_bench to profile")
    p.add_argument("--kernel", default="rasterize_backward_kernel", help="kernel name (regular expression)")
    p.add_argument("--launches", type=int, default=40, help="launches to profile (all cases at --runs 2)")
    p.add_argument("--csv", help="summarise this ncu CSV instead of running ncu")
    p.add_argument("--csv_out", help="also keep the raw ncu CSV here")
    p.add_argument("--build", default="", help="commit of the profiled build, copied into each line")
    p.add_argument("--machine", default=os.environ.get("MACHINE", ""), help="GPU and host, copied into each line")
    a = p.parse_args()
    if not a.csv and not a.bench:
        p.error("give --bench (profile now) or --csv (summarise an earlier profile)")
    text = open(a.csv).read() if a.csv else run_ncu(a.bench, a.kernel, a.launches)
    if a.csv_out:
        with open(a.csv_out, "w") as f:
            f.write(text)
    for line in summarise(text):
        print(json.dumps({"kernel": a.kernel, "build": a.build, "machine": a.machine, "profiler": "ncu", **line}))


if __name__ == "__main__":
    main()

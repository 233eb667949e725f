#!/usr/bin/env python3
"""Initialisation time and point count per scene, view count and method, through `gaps init`.

Each case runs `gaps init` once with an empty cache (so it computes, never reads a cached cloud) and records
the command's wall seconds (loading, SIFT, PatchMatch or the sweep, fusion and writing the outputs), the
method that made the points (`auto` resolved) and their count, parsed from the command's own summary line.
Standard library only, like harness.py.

  bench/init_times.py --gaps build/client/gaps --data ../shared/data --out init_times.jsonl \\
      [--device cuda] [--methods auto,mvs,sweep,sparse] [--cases llff/fern:3,6,9 mipnerf360/bonsai:12,24]
"""
import argparse
import json
import platform
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from harness import describe_device, git_commit

SUMMARY = re.compile(r"^init: (\w+), (\d+) points from (\d+) training views", re.MULTILINE)
DEFAULT_CASES = ["llff/fern:3,6,9", "mipnerf360/bonsai:12,24"]


def parse_cases(specs):
    """"path:3,6,9" -> [(path, 3), (path, 6), (path, 9)]."""
    cases = []
    for spec in specs:
        path, _, views = spec.partition(":")
        if not views:
            raise SystemExit(f"case {spec!r}: expected PATH:VIEWS[,VIEWS...]")
        cases.extend((path, int(v)) for v in views.split(","))
    return cases


def parse_summary(output):
    """(method, points) from `gaps init`'s last summary line, or None when it printed none."""
    found = SUMMARY.findall(output)
    return (found[-1][0], int(found[-1][1])) if found else None


def time_case(gaps, data, path, views, method, device, resolution):
    with tempfile.TemporaryDirectory() as tmp:
        cmd = [gaps, "init", f"--scene={Path(data) / path}", f"--views={views}", f"--init={method}",
               f"--resolution={resolution}", f"--device={device}", f"--init-cache={Path(tmp) / 'cache'}",
               f"--out={Path(tmp) / 'out'}"]
        start = time.monotonic()
        done = subprocess.run(cmd, capture_output=True, text=True)
        wall = time.monotonic() - start
    output = done.stdout + done.stderr
    summary = parse_summary(output)
    row = {"scene": Path(path).name, "views": views, "method": method, "device": device,
           "resolution": resolution, "exit_status": done.returncode, "wall_seconds": round(wall, 3),
           "method_used": summary[0] if summary else None, "points": summary[1] if summary else None,
           "log": [line for line in output.splitlines() if line.startswith(("init:", "budget:", "warning:"))]}
    if done.returncode != 0 or summary is None:
        row["error"] = output.strip().splitlines()[-1] if output.strip() else f"exit status {done.returncode}"
    return row


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--gaps", default="build/client/gaps", help="the gaps binary")
    parser.add_argument("--data", required=True, help="root the cases' scene paths are relative to")
    parser.add_argument("--out", required=True, help="JSON lines, one row per case (appended)")
    parser.add_argument("--device", default="cpu", help="cpu, cuda or cuda:N")
    parser.add_argument("--resolution", type=int, default=8)
    parser.add_argument("--methods", default="auto,mvs,sweep,sparse")
    parser.add_argument("--cases", nargs="+", default=DEFAULT_CASES, help="PATH:VIEWS[,VIEWS...] under --data")
    parser.add_argument("--commit", default="", help="recorded in every row (default: git HEAD of this checkout)")
    args = parser.parse_args(argv)
    recorded = {"commit": args.commit or git_commit(),
                "machine": f"{platform.node()}: {describe_device(None, args.device)}"}
    failed = 0
    with open(args.out, "a") as out:
        for path, views in parse_cases(args.cases):
            for method in args.methods.split(","):
                row = time_case(args.gaps, args.data, path, views, method, args.device, args.resolution)
                row.update(recorded)
                out.write(json.dumps(row) + "\n")
                out.flush()
                failed += "error" in row
                print(f"{row['scene']} {views} {method}: {row['method_used']} {row['points']} points "
                      f"{row['wall_seconds']:.2f} s" + (f" FAILED: {row['error']}" if "error" in row else ""),
                      flush=True)
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())

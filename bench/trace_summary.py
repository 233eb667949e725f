"""Ranks what a profiler trace (Chrome JSON from train_throughput_bench --trace) spends its time on:
GPU kernels and copies by total device time, host operations by total wall time (inclusive, top-level
ATen calls and autograd nodes), and the iteration's wall time split between GPU busy and idle.
    python3 bench/trace_summary.py TRACE.json [--iterations N] [--top 25]
"""
import argparse
import collections
import json


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("trace")
    ap.add_argument("--iterations", type=int, default=50)
    ap.add_argument("--top", type=int, default=25)
    args = ap.parse_args()
    events = json.load(open(args.trace))["traceEvents"]
    complete = [e for e in events if e.get("ph") == "X" and "dur" in e]
    gpu = [e for e in complete if e.get("cat") in ("kernel", "gpu_memcpy", "gpu_memset")]
    host = [e for e in complete if e.get("cat") in ("cpu_op", "user_annotation")]
    runtime = [e for e in complete if e.get("cat") == "cuda_runtime"]
    n = args.iterations

    def table(title, rows, unit_total):
        print(f"\n{title}")
        print(f"{'ms/it':>8} {'calls/it':>9}  name")
        for name, (total, count) in rows[: args.top]:
            print(f"{total / 1e3 / n:8.3f} {count / n:9.1f}  {name[:110]}")
        print(f"{unit_total / 1e3 / n:8.3f} {'':>9}  (all)")

    def aggregate(evs):
        acc = collections.defaultdict(lambda: [0.0, 0])
        for e in evs:
            acc[e["name"]][0] += e["dur"]
            acc[e["name"]][1] += 1
        return sorted(acc.items(), key=lambda kv: -kv[1][0])

    table("GPU kernels, copies and memsets", aggregate(gpu), sum(e["dur"] for e in gpu))
    table("CUDA runtime calls (host)", aggregate(runtime), sum(e["dur"] for e in runtime))
    # Host ops: only those not nested in another op of the same thread, so totals do not double count.
    host.sort(key=lambda e: (e["tid"], e["ts"]))
    top, end_by_tid = [], {}
    for e in host:
        if e["ts"] >= end_by_tid.get(e["tid"], -1):
            top.append(e)
            end_by_tid[e["tid"]] = e["ts"] + e["dur"]
    table("Host operations (outermost per thread)", aggregate(top), sum(e["dur"] for e in top))
    if complete:
        span = max(e["ts"] + e["dur"] for e in complete) - min(e["ts"] for e in complete)
        busy = sum(e["dur"] for e in gpu)
        print(f"\nwall {span / 1e3 / n:.3f} ms/it, GPU busy {busy / 1e3 / n:.3f} ms/it "
              f"({100 * busy / max(span, 1):.0f}%), {len(gpu) / n:.0f} GPU launches/it")


if __name__ == "__main__":
    main()

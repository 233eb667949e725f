#!/usr/bin/env python3
"""What the services cost against the same run in process: one scene's full method trained by `gaps train`, and
through `gaps-trainer` + `gaps-worker` (reproject) for each hand-over of the pseudo-view payloads.

Cases (--cases, run in this order for every seed, after one unrecorded in-process warm-up that fills the init cache
every run then shares, so that initialisation does not differ between cases):

  in-process        gaps train
  float32-socket    the services, float32 payloads in the gRPC messages (the hand-over before compact encoding)
  compact-socket    colour and alpha as bytes, depth in half precision, in the messages
  compact-shared    compact, through shared memory (the default on one host)
  float32-shared    float32 through shared memory

Per case and seed one JSON line: wall time of the run (in process: the process; services: submit to the end of
`gaps watch`), training seconds, PSNR / SSIM / LPIPS, and the phases' sums (sections, generator stages such as
client_encode / worker_decode / transfer, counters such as request_bytes). --trainer_device and --worker_device
place the two services; the worker's reproject backend computes on the CPU wherever it is told to run.

  python3 bench/service_overhead.py --build build --scene ../shared/data/llff/fern --out bench/results/X.jsonl \\
      [--seeds 0] [--views 3] [--resolution 8] [--device cuda] [--cases ...] [--label alone]
"""
import argparse
import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from placements_bench import Service, phase_breakdown  # noqa: E402

REPO = Path(__file__).resolve().parent.parent
CASES = {
    "float32-socket": ["--worker_encoding", "float32", "--noworker_shared_memory"],
    "compact-socket": ["--worker_encoding", "compact", "--noworker_shared_memory"],
    "compact-shared": ["--worker_encoding", "compact", "--worker_shared_memory"],
    "float32-shared": ["--worker_encoding", "float32", "--worker_shared_memory"],
}


def run_flags(args, seed):
    return ["--views", args.views, "-r", args.resolution, "--variant", "full", "--device", args.device,
            "--seed", str(seed), *args.run_flags]


def results(folder):
    metrics = json.loads((folder / "metrics.json").read_text()) if (folder / "metrics.json").exists() else {}
    phases = json.loads((folder / "phases.json").read_text()) if (folder / "phases.json").exists() else []
    return {"train_seconds": metrics.get("train_seconds"), "psnr": metrics.get("psnr"), "ssim": metrics.get("ssim"),
            "lpips": metrics.get("lpips"), "iterations": metrics.get("iterations"),
            # The schedule the run had (asynchronous, 250, by default since 2026-11-30; 0: synchronous).
            "async_iterations": metrics.get("gaps", {}).get("async_iterations"),
            "num_gaussians": metrics.get("num_gaussians"), **phase_breakdown(phases)}


def in_process(args, seed, out, env):
    shutil.rmtree(out, ignore_errors=True)  # a failed run must not report an earlier run's metrics
    start = time.time()
    done = subprocess.run([str(args.build / "client" / "gaps"), "train", str(args.scene), "-o", str(out), "--quiet",
                           "--init-cache", str(args.init_cache), *run_flags(args, seed)], env=env,
                          capture_output=True, text=True)
    wall = time.time() - start
    if done.returncode != 0:
        print(done.stderr[-3000:], file=sys.stderr)
    return {"succeeded": done.returncode == 0, "wall_seconds": round(wall, 2), **results(out)}


def through_services(args, case, seed, work, env):
    work.mkdir(parents=True, exist_ok=True)
    gaps = str(args.build / "client" / "gaps")
    worker = Service("gaps-worker", [str(args.build / "diffusion_worker" / "service" / "gaps-worker"), "--listen",
                                     "127.0.0.1:0", "--backend", "reproject", "--device", args.worker_device],
                     work / "worker.log", env)
    trainer = None
    try:
        port = worker.wait_for_port(120)
        trainer = Service("gaps-trainer", [str(args.build / "server" / "gaps-trainer"), "--listen", "127.0.0.1:0",
                                           "--data_dir", str(work / "data"), "--device", args.device,
                                           "--init_cache", str(args.init_cache), "--workers", f"127.0.0.1:{port}",
                                           *CASES[case]], work / "trainer.log", env)
        address = f"127.0.0.1:{trainer.wait_for_port(120)}"
        start = time.time()
        submitted = subprocess.run([gaps, "submit", str(args.scene), "--trainer", address, *run_flags(args, seed)],
                                   env=env, capture_output=True, text=True, check=True)
        job = submitted.stdout.strip().splitlines()[0]
        watch = subprocess.run([gaps, "watch", job, "--quiet", "--trainer", address], env=env)
        wall = time.time() - start
        shutil.rmtree(work / "fetched", ignore_errors=True)
        subprocess.run([gaps, "fetch", job, "-o", str(work / "fetched"), "--trainer", address], env=env,
                       capture_output=True)
    finally:
        if trainer:
            trainer.stop()
        worker.stop()
    return {"succeeded": watch.returncode == 0, "wall_seconds": round(wall, 2), **results(work / "fetched")}


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--build", type=Path, default=REPO / "build")
    parser.add_argument("--scene", type=Path, default=REPO.parent / "shared" / "data" / "llff" / "fern")
    parser.add_argument("--views", default="3")
    parser.add_argument("--resolution", default="8")
    parser.add_argument("--device", default="cuda", help="the trainer's device (both paths)")
    parser.add_argument("--worker_device", default="cuda", help="gaps-worker --device")
    parser.add_argument("--seeds", default="0")
    parser.add_argument("--cases", default="in-process,float32-socket,compact-socket,compact-shared")
    parser.add_argument("--work", type=Path, default=Path("/tmp/gaps_service_overhead"))
    parser.add_argument("--init_cache", type=Path, default=None, help="default: WORK/init_cache")
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--label", default="", help="recorded with each row, e.g. alone or busy host")
    parser.add_argument("--commit", default="")
    parser.add_argument("--no_warm_up", action="store_true", help="the init cache is warm already")
    parser.add_argument("--run_flags", nargs=argparse.REMAINDER, default=[],
                        help="more flags for both gaps train and gaps submit (last on the line)")
    args = parser.parse_args()
    cases = args.cases.split(",")
    for case in cases:
        if case != "in-process" and case not in CASES:
            raise SystemExit(f"unknown case {case}: in-process, {', '.join(CASES)}")
    args.init_cache = args.init_cache or args.work / "init_cache"
    env = dict(os.environ)  # $GAPS_CACHE as the set-up made it: the LPIPS weights
    commit = args.commit or subprocess.run(["git", "-C", str(REPO), "rev-parse", "--short", "HEAD"],
                                           capture_output=True, text=True).stdout.strip()
    machine = subprocess.run(["nvidia-smi", "-L"], capture_output=True, text=True).stdout.strip().splitlines() \
        if args.device.startswith("cuda") else []
    if not args.no_warm_up:
        print(json.dumps({"warm_up": in_process(args, 0, args.work / "warm_up", env)["wall_seconds"]}), flush=True)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    for seed in [int(s) for s in args.seeds.split(",")]:
        for case in cases:
            folder = args.work / f"{case}_s{seed}"
            row = in_process(args, seed, folder, env) if case == "in-process" else \
                through_services(args, case, seed, folder, env)
            row = {"bench": "service_overhead", "case": case, "seed": seed, "label": args.label,
                   "run_flags": " ".join(args.run_flags), "commit": commit, "gpus": machine,
                   "cpus": os.cpu_count(), "scene": args.scene.name, "views": args.views,
                   "resolution": args.resolution, **row}
            print(json.dumps(row), flush=True)
            with open(args.out, "a") as f:
                f.write(json.dumps(row) + "\n")


if __name__ == "__main__":
    main()

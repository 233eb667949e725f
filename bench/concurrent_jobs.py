#!/usr/bin/env python3
"""Jobs trained at once by one trainer: what each job's initialisation and training cost, with the CPU threads
shared out among the jobs (`gaps-trainer --threads-per-job 0`, the default) and with every job taking all of
them (`--threads-per-job <the process's threads>`, what the trainer did before it shared them out).

Cases `sdxl-keeps` and `sdxl-retrains`: --variant full jobs sharing one `gaps-worker --backend sdxl` (random
full-size weights, written once into WORK as placements_bench.py writes them; more backend options with
--worker_options) on --device, whose phases alternate between the jobs' scenes: the worker installs each
scene's LoRA adaptation again when the scene comes back (`--keep_scene_adaptations`, its default) or trains it
anew each time (`--nokeep_scene_adaptations`, what it did before). Their rows add the phases' sums (the
worker's `scene_switch` seconds and counts among the generator stages and counters).

Per case one trainer on a fresh data folder (so every job computes its initialisation: the init cache is empty,
and jobs that start together all miss it), --jobs copies of one vanilla job submitted at once with
--concurrency equal to --jobs; per job one JSON line: the case, the threads its log reports, init_seconds and
train_seconds from its metrics.json, its wall time from submission to its end. Cases run one after the other
in the order given, so compare them within one run.

  python3 bench/concurrent_jobs.py --build build --scene ../shared/data/llff/fern --out X.jsonl \\
      [--jobs 2] [--views 3] [--resolution 8] [--iterations 200] [--device cpu] [--cases shared-out,every-core] \\
      [--job_flags --init mvs --patchmatch-max-image-side 320 ...]   (default: the job's defaults, --init auto)
"""
import argparse
import json
import os
import re
import shutil
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from harness import describe_device, git_commit  # noqa: E402
from placements_bench import Service, ensure_weights, phase_breakdown  # noqa: E402

REPO = Path(__file__).resolve().parent.parent
THREADS = re.compile(r"trains with (\d+) CPU thread")


SDXL_CASES = {"sdxl-keeps": "--keep_scene_adaptations", "sdxl-retrains": "--nokeep_scene_adaptations"}


def case_flags(case, process_threads):
    if case in ("shared-out", *SDXL_CASES):
        return ["--threads-per-job", "0"]
    if case == "every-core":
        return ["--threads-per-job", str(process_threads)]
    raise SystemExit(f"--cases: unknown case '{case}' (shared-out, every-core, sdxl-keeps, sdxl-retrains)")


def job_flags(args, case):
    variant = "full" if case in SDXL_CASES else "vanilla"
    return ["--views", args.views, "-r", args.resolution, "--variant", variant, "--device", args.device,
            "--iterations", args.iterations, *args.job_flags]


def run_job(gaps, address, scene, flags, fetch_to, env):
    start = time.time()
    submitted = subprocess.run([gaps, "submit", str(scene), "--trainer", address, *flags], env=env,
                               capture_output=True, text=True, check=True)
    job = submitted.stdout.strip().splitlines()[0]
    watched = subprocess.run([gaps, "watch", job, "--trainer", address], env=env, capture_output=True, text=True)
    wall = time.time() - start
    subprocess.run([gaps, "fetch", job, "-o", str(fetch_to), "--trainer", address], env=env, capture_output=True)
    metrics_file, phases_file = fetch_to / "metrics.json", fetch_to / "phases.json"
    metrics = json.loads(metrics_file.read_text()) if metrics_file.exists() else {}
    phases = json.loads(phases_file.read_text()) if phases_file.exists() else []
    threads = THREADS.search(watched.stdout + watched.stderr)
    return {"job": job, "succeeded": watched.returncode == 0, "wall_seconds": round(wall, 2),
            "threads": int(threads.group(1)) if threads else None, "init_seconds": metrics.get("init_seconds"),
            "train_seconds": metrics.get("train_seconds"), "psnr": metrics.get("psnr"),
            **(phase_breakdown(phases) if phases else {})}


def start_worker(args, case, work, env):
    """The one sdxl worker the jobs of an sdxl case share, and its address."""
    options = {**ensure_weights(args.build, args.work, sys.executable), **args.worker_options}
    worker = Service("gaps-worker", [str(args.build / "diffusion_worker" / "service" / "gaps-worker"), "--listen",
                                     "127.0.0.1:0", "--backend", "sdxl", "--device", args.device,
                                     "--backend_options", json.dumps(options), SDXL_CASES[case]],
                     work / "worker.log", env)
    return worker, f"127.0.0.1:{worker.wait_for_port(600)}"


def run_case(args, case, process_threads, env):
    work = args.work / case
    shutil.rmtree(work, ignore_errors=True)
    work.mkdir(parents=True)
    worker, pool_flags = None, []
    if case in SDXL_CASES:
        worker, address = start_worker(args, case, work, env)
        pool_flags = ["--workers", address]
    trainer = Service("gaps-trainer", [str(args.build / "server" / "gaps-trainer"), "--listen", "127.0.0.1:0",
                                       "--data_dir", str(work / "data"), "--device", args.device,
                                       "--concurrency", str(args.jobs), *case_flags(case, process_threads),
                                       *pool_flags],
                      work / "trainer.log", env)
    try:
        address = f"127.0.0.1:{trainer.wait_for_port(120)}"
        gaps = str(args.build / "client" / "gaps")
        with ThreadPoolExecutor(args.jobs) as pool:
            futures = [pool.submit(run_job, gaps, address, args.scene, job_flags(args, case), work / f"fetched{i}",
                                   env) for i in range(args.jobs)]
            return [f.result() for f in futures]
    finally:
        trainer.stop()
        if worker:
            worker.stop()


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--build", type=Path, default=REPO / "build")
    parser.add_argument("--scene", type=Path, default=REPO.parent / "shared" / "data" / "llff" / "fern")
    parser.add_argument("--jobs", type=int, default=2)
    parser.add_argument("--views", default="3")
    parser.add_argument("--resolution", default="8")
    parser.add_argument("--iterations", default="200")
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--cases", default="shared-out,every-core")
    parser.add_argument("--work", type=Path, default=Path("/tmp/gaps_concurrent_jobs"))
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--label", default="")
    parser.add_argument("--worker_options", type=json.loads, default={},
                        help='more sdxl backend options (JSON) for the sdxl cases, e.g. \'{"cuda_graphs": true}\'')
    parser.add_argument("--job_flags", nargs=argparse.REMAINDER, default=[],
                        help="the rest: more `gaps submit` flags, e.g. --init mvs --patchmatch-max-image-side 320")
    args = parser.parse_args()
    env = dict(os.environ)
    process_threads = int(env.get("OMP_NUM_THREADS") or len(os.sched_getaffinity(0)))
    header = {"bench": "concurrent_jobs", "commit": git_commit(), "machine": describe_device(None, args.device),
              "cores": len(os.sched_getaffinity(0)), "process_threads": process_threads, "jobs": args.jobs,
              "scene": args.scene.name, "views": args.views, "resolution": args.resolution,
              "iterations": args.iterations, "job_flags": " ".join(args.job_flags), "device": args.device, "label": args.label,
              "worker_options": args.worker_options,
              "date": time.strftime("%Y-%m-%d")}
    args.out.parent.mkdir(parents=True, exist_ok=True)
    for case in args.cases.split(","):
        rows = run_case(args, case, process_threads, env)
        with args.out.open("a") as out:
            for row in rows:
                out.write(json.dumps({**header, "case": case, **row}) + "\n")
        for row in rows:
            switch = row.get("generator_stage_seconds", {}).get("scene_switch")
            print(f"{case}: threads {row['threads']}, init {row['init_seconds']} s, train {row['train_seconds']} s, "
                  f"wall {row['wall_seconds']} s, scene switches {switch} s{'' if row['succeeded'] else ' (FAILED)'}",
                  flush=True)


if __name__ == "__main__":
    main()

#!/usr/bin/env python3
"""The design's two placements of the services, end to end with the whole sdxl stack (random full-size weights).

Starts `gaps-worker` and `gaps-trainer` as a user would, submits one scene through `gaps submit`, follows it with
`gaps watch`, fetches the results with `gaps fetch`, and records per case: the GPU memory the driver reports per
process and per GPU (sampled with nvidia-smi, not only the caching allocators), the job's wall time, the trainer's
training time and allocator peak (metrics.json), and where each diffusion phase's time went (phases.json: the
trainer's sections and the generator's stages: AdaptScene with the LoRA training, img2img, SD2 inpainting and
its first load, transfer). Cases (--cases, in order):

  vanilla          the trainer alone on GPU 0 (--variant vanilla): what the method's time is compared with
  reproject        the weight-free backend (worker on the CPU), trainer on GPU 0: the method's time without SDXL
  one-card         trainer and sdxl worker on GPU 0, each allocator capped (--trainer_gib, --worker_gib) so that
                   the pair must fit a 24 GB card (--card_gib): the run proves the fit instead of assuming it
  two-gpus         trainer on GPU 0, sdxl worker on GPU 1, uncapped
  two-gpus-both    trainer on GPU 0, one sdxl worker on each GPU, uncapped: the trainer spreads each phase's
                   pseudo-views over both (gaps-trainer --worker_fan_out, its default)
  weights          nothing but writing the weights

The weights (SDXL base from `generator_bench --write_model`; ControlNet depth, IP-Adapter + ViT-H image encoder,
SD2 inpainting, Depth-Anything from `make_random_generator_weights.py`, which needs diffusers) are written into
WORK once and reused. Random weights make the pseudo-views meaningless: admission may reject them; phases count
as run. One JSON line per case goes to --out; a case whose worker logged an empty CUDA-graph capture is marked
`"timing_valid": false` (its replays skipped the UNet).

  python3 bench/placements_bench.py --build build --scene ../shared/data/llff/fern --work /tmp/placements \
      --out bench/results/placements_gpu_DATE.jsonl [--cases reproject,one-card,two-gpus] \
      [--worker_options '{"cuda_graphs": true}'] [--trainer_flags '--worker_adaptation_grace_s 1e6'] \
      [--submit_flags --async-iterations 500]

Jobs run with the trainer's defaults unless --submit_flags says otherwise: asynchronous phases (250) since
2026-11-30, so the synchronous rows recorded before need `--submit_flags --async-iterations 0` to be repeated. Each
row records the schedule its job had (`async_iterations`, from metrics.json).
"""
import argparse
import json
import os
import re
import shlex
import shutil
import subprocess
import sys
import threading
import time
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
GIB = 1 << 30


def run(cmd, **kwargs):
    print("+", " ".join(str(c) for c in cmd), flush=True)
    return subprocess.run([str(c) for c in cmd], check=True, **kwargs)


def ensure_weights(build, work, python):
    sdxl, components = work / "sdxl", work / "components"
    if not (sdxl / "model_index.json").exists():
        run([build / "bench" / "generator_bench", "--sdxl_dir", sdxl, "--write_model", "--write_only"])
    if not (components / "done.json").exists():
        run([python, REPO / "bench" / "make_random_generator_weights.py", "--sdxl_dir", sdxl, "--out", components])
    return {
        "weights": str(sdxl),
        "dtype": "float16",
        "controlnet": str(components / "controlnet"),
        "ip_adapter": str(components / "ip_adapter" / "ip-adapter_sdxl_vit-h.safetensors"),
        "image_encoder": str(components / "ip_adapter" / "image_encoder"),
        "inpaint": str(components / "sd2_inpaint"),
        "depth_anything": str(components / "depth_anything"),
        "prompt": "a photograph of the scene",
    }


class GpuMemorySampler:
    """Peak used memory per GPU and per process as the driver reports it (nvidia-smi), every `period` s."""

    def __init__(self, period=0.2):
        self.period = period
        self.gpu_peak_mib, self.gpu_base_mib, self.pid_peak_mib = {}, {}, {}
        self._stop = threading.Event()
        self.gpu_base_mib = self._gpus()
        self._thread = threading.Thread(target=self._loop, daemon=True)

    @staticmethod
    def _query(args):
        out = subprocess.run(["nvidia-smi", *args, "--format=csv,noheader,nounits"], capture_output=True, text=True)
        return [line.split(", ") for line in out.stdout.strip().splitlines() if line.strip()]

    def _gpus(self):
        return {int(i): float(m) for i, m in self._query(["--query-gpu=index,memory.used"])}

    def _loop(self):
        while not self._stop.is_set():
            for gpu, mib in self._gpus().items():
                self.gpu_peak_mib[gpu] = max(self.gpu_peak_mib.get(gpu, 0.0), mib)
            for row in self._query(["--query-compute-apps=pid,used_memory"]):
                if len(row) == 2 and row[1].strip().isdigit():
                    pid = int(row[0])
                    self.pid_peak_mib[pid] = max(self.pid_peak_mib.get(pid, 0.0), float(row[1]))
            self._stop.wait(self.period)

    def __enter__(self):
        self._thread.start()
        return self

    def __exit__(self, *exc):
        self._stop.set()
        self._thread.join()


class Service:
    """A service process whose log goes to a file; the port it prints once it listens is read back."""

    def __init__(self, name, cmd, log_path, env):
        self.name, self.log_path = name, log_path
        print("+", " ".join(cmd), flush=True)
        self.log = open(log_path, "w")
        self.proc = subprocess.Popen(cmd, stdout=self.log, stderr=subprocess.STDOUT, env=env)

    def wait_for_port(self, timeout):
        deadline = time.time() + timeout
        while time.time() < deadline:
            match = re.search(r"on port (\d+)", self.log_path.read_text())
            if match:
                return int(match.group(1))
            if self.proc.poll() is not None:
                break
            time.sleep(0.5)
        raise RuntimeError(f"{self.name} did not start:\n{self.log_path.read_text()[-3000:]}")

    def stop(self):
        if self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(60)
            except subprocess.TimeoutExpired:
                self.proc.kill()
        self.log.close()


def phase_breakdown(phases):
    """Sums of the phases' sections, generator stages and generator counters (bytes, the sdxl backend's batches and
    denoising steps), and the admission counts."""
    sections, stages, counters = {}, {}, {}
    admitted = rejected = skipped = 0
    strengths = []
    for p in phases:
        for totals, entry in ((sections, "seconds"), (stages, "generator_stages"), (counters, "generator_counters")):
            for key, value in p.get(entry, {}).items():
                totals[key] = totals.get(key, 0.0) + value
        skipped += bool(p.get("skipped"))
        for s in p.get("selection", []):
            admitted += bool(s.get("admitted"))
            rejected += not s.get("admitted")
            if "strength" in s:
                strengths.append(s["strength"])
    # The first phase carries the scene adaptation (sdxl's LoRA training), which a second worker cannot shorten.
    first = phases[0].get("seconds", {}).get("generation") if phases else None
    return {"phases": len(phases), "phases_skipped": skipped, "pseudo_views_admitted": admitted,
            "pseudo_views_rejected": rejected, "phase_seconds": {k: round(v, 3) for k, v in sections.items()},
            "first_phase_generation_seconds": round(first, 3) if first is not None else None,
            "generator_stage_seconds": {k: round(v, 3) for k, v in stages.items()}, "generator_counters": counters,
            # The img2img strengths the phases asked for (a request runs int(steps x strength) denoising steps).
            "request_strengths": {"count": len(strengths), "min": min(strengths), "max": max(strengths),
                                  "mean": sum(strengths) / len(strengths)} if strengths else None}


# LibTorch's warning when a capture recorded nothing: the replays of that graph would skip the UNet, so the
# case's times would not be those of the method (a capture on another device's stream did exactly that).
EMPTY_GRAPH_WARNING = "The CUDA Graph is empty"


def empty_graph_warnings(logs):
    """How many empty CUDA-graph captures each worker's log reports; a timing with any of them is void."""
    return {name: (path.read_text(errors="replace").count(EMPTY_GRAPH_WARNING) if path.exists() else None)
            for name, path in logs.items()}


def worker_name(k):
    """How a row names the case's k-th worker (its log is worker{k}.log)."""
    return "worker" if k == 0 else f"worker{k}"


def case_layout(case, args, backend_options):
    """The case's workers (gaps-worker flags, GPU, allocator cap), the trainer's device and cap, and the variant."""
    sdxl = ["--backend", "sdxl", "--backend_options", json.dumps(backend_options)]
    if case == "vanilla":
        return [], ("cuda:0", 0.0), "vanilla"
    if case == "reproject":
        return [(["--backend", "reproject"], None, 0.0)], ("cuda:0", 0.0), "full"
    if case == "one-card":
        return [([*sdxl, "--device", "cuda:0"], 0, args.worker_gib)], ("cuda:0", args.trainer_gib), "full"
    if case == "two-gpus":
        return [([*sdxl, "--device", "cuda:1"], 1, 0.0)], ("cuda:0", 0.0), "full"
    if case == "two-gpus-both":
        return ([([*sdxl, "--device", "cuda:1"], 1, 0.0), ([*sdxl, "--device", "cuda:0"], 0, 0.0)],
                ("cuda:0", 0.0), "full")
    raise SystemExit(f"unknown case {case} (vanilla, reproject, one-card, two-gpus, two-gpus-both)")


def run_case(case, args, backend_options, env):
    gaps = args.build / "client" / "gaps"
    work = args.work / case
    # A run before this one left its job database (which a trainer would resume) and its fetched files.
    shutil.rmtree(work, ignore_errors=True)
    work.mkdir(parents=True, exist_ok=True)
    worker_layout, (trainer_device, trainer_cap), variant = case_layout(case, args, backend_options)
    caps = (trainer_cap, max((cap for _, _, cap in worker_layout), default=0.0))

    with GpuMemorySampler() as sampler:
        start = time.time()
        workers, trainer = [], None
        try:
            # The workers load at once (each its own weights), as a deployment starts them.
            for k, (flags, _, cap) in enumerate(worker_layout):
                workers.append(Service(f"gaps-worker {k}",
                                       [str(args.build / "diffusion_worker" / "service" / "gaps-worker"), "--listen",
                                        "127.0.0.1:0", "--gpu_memory_gib", str(cap), *flags],
                                       work / f"worker{k}.log", env))
            worker_ports = [w.wait_for_port(600) for w in workers]
            worker_ready = time.time() - start
            pool = ["--workers", ",".join(f"127.0.0.1:{p}" for p in worker_ports)] if workers else []
            trainer = Service("gaps-trainer", [str(args.build / "server" / "gaps-trainer"), "--listen", "127.0.0.1:0",
                                               "--data_dir", str(work / "data"), "--device", trainer_device,
                                               "--gpu_memory_gib", str(trainer_cap), *pool, *args.trainer_flags],
                              work / "trainer.log", env)
            address = f"127.0.0.1:{trainer.wait_for_port(120)}"
            submitted = time.time()
            out = run([gaps, "submit", args.scene, "--views", args.views, "-r", args.resolution, "--variant", variant,
                       "--device", trainer_device, "--trainer", address,
                       *(args.submit_flags if variant != "vanilla" else [])],
                      capture_output=True, text=True).stdout
            job = out.strip().splitlines()[0]
            watch = subprocess.run([str(gaps), "watch", job, "--quiet", "--trainer", address])
            job_seconds = time.time() - submitted
            run([gaps, "fetch", job, "-o", work / "fetched", "--trainer", address], capture_output=True)
        finally:
            if trainer:
                trainer.stop()
            for w in workers:
                w.stop()
    fetched = work / "fetched"
    metrics = json.loads((fetched / "metrics.json").read_text()) if (fetched / "metrics.json").exists() else {}
    phases = json.loads((fetched / "phases.json").read_text()) if (fetched / "phases.json").exists() else []
    pids = {"trainer": trainer.proc.pid,
            **{worker_name(k): w.proc.pid for k, w in enumerate(workers)}}
    per_process = {name: sampler.pid_peak_mib.get(pid) for name, pid in pids.items()}
    empty_graphs = empty_graph_warnings({worker_name(k): work / f"worker{k}.log" for k in range(len(workers))})
    if any(empty_graphs.values()):
        print(f"VOID: a worker captured empty CUDA graphs {empty_graphs}: its replays skipped the UNet",
              file=sys.stderr, flush=True)
    gpus_used = sorted({0} | {gpu for _, gpu, _ in worker_layout if gpu is not None})
    gpu_peak = {g: sampler.gpu_peak_mib.get(g, 0.0) - sampler.gpu_base_mib.get(g, 0.0) for g in gpus_used}
    row = {
        "case": case, "variant": variant, "workers": len(workers),
        "submit_flags": args.submit_flags if variant != "vanilla" else [], "trainer_flags": args.trainer_flags,
        "scene": str(args.scene), "views": args.views, "resolution": args.resolution,
        "succeeded": watch.returncode == 0, "job_wall_seconds": round(job_seconds, 2),
        "worker_start_seconds": round(worker_ready, 2) if workers else None,
        "train_seconds": metrics.get("train_seconds"), "psnr": metrics.get("psnr"),
        # The schedule the job had (asynchronous, 250, by default since 2026-11-30; 0: synchronous).
        "async_iterations": metrics.get("gaps", {}).get("async_iterations"),
        "iterations": metrics.get("iterations"), "num_gaussians": metrics.get("num_gaussians"),
        "trainer_allocator_peak_gib": round(metrics.get("peak_memory", {}).get("bytes", 0) / GIB, 3),
        "caps_gib": {"trainer": caps[0], "worker": caps[1]},
        "driver_peak_gib_per_process": {k: (round(v / 1024, 3) if v is not None else None)
                                        for k, v in per_process.items()},
        "driver_peak_gib_per_gpu": {str(g): round(v / 1024, 3) for g, v in gpu_peak.items()},
        "worker_empty_cuda_graphs": empty_graphs, "timing_valid": not any(empty_graphs.values()),
        **phase_breakdown(phases),
    }
    if case == "one-card":
        row["card_gib"] = args.card_gib
        row["fits_card"] = gpu_peak[0] / 1024 <= args.card_gib
    return row


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--build", type=Path, default=REPO / "build")
    parser.add_argument("--scene", type=Path, default=REPO.parent / "shared" / "data" / "llff" / "fern")
    parser.add_argument("--views", default="3")
    parser.add_argument("--resolution", default="8")
    parser.add_argument("--work", type=Path, default=Path("/tmp/gaps_placements"))
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--cases", default="reproject,one-card,two-gpus")
    parser.add_argument("--trainer_gib", type=float, default=3.0, help="trainer's allocator cap in one-card")
    parser.add_argument("--worker_gib", type=float, default=17.0, help="worker's allocator cap in one-card")
    parser.add_argument("--card_gib", type=float, default=23.0,
                        help="what the pair may use on the shared GPU as the driver counts it (a 24 GB card "
                             "has 23.99 GiB, some of it the driver's)")
    parser.add_argument("--python", default=sys.executable, help="Python with diffusers, for the weights")
    parser.add_argument("--commit", default="")
    parser.add_argument("--worker_options", type=json.loads, default={},
                        help='more sdxl backend options (JSON) over the bench\'s, e.g. \'{"cuda_graphs": true}\'')
    parser.add_argument("--trainer_flags", type=shlex.split, default=[],
                        help="more gaps-trainer flags, one string, e.g. '--worker_adaptation_grace_s 1e6'")
    parser.add_argument("--submit_flags", nargs=argparse.REMAINDER, default=[],
                        help="more `gaps submit` flags, e.g. --iterations 3000 (last on the line)")
    args = parser.parse_args()
    args.work.mkdir(parents=True, exist_ok=True)
    cases = args.cases.split(",")
    needs_sdxl = any(c not in ("vanilla", "reproject") for c in cases)
    backend_options = ensure_weights(args.build, args.work, args.python) if needs_sdxl else {}
    if needs_sdxl:
        backend_options.update(args.worker_options)
    # nvidia-smi numbers GPUs by PCI bus; CUDA's own order may differ unless told.
    env = dict(os.environ, CUDA_DEVICE_ORDER="PCI_BUS_ID")
    machine = subprocess.run(["nvidia-smi", "-L"], capture_output=True, text=True).stdout.strip().splitlines()
    commit = args.commit or subprocess.run(["git", "-C", str(REPO), "rev-parse", "--short", "HEAD"],
                                           capture_output=True, text=True).stdout.strip()
    args.out.parent.mkdir(parents=True, exist_ok=True)
    for case in cases:
        if case == "weights":  # only write them (a run split over several sittings)
            continue
        row = {"bench": "placements", "commit": commit, "gpus": machine, "cpus": os.cpu_count(),
               "worker_options": args.worker_options if case not in ("vanilla", "reproject") else {},
               **run_case(case, args, backend_options, env)}
        print(json.dumps(row), flush=True)
        with open(args.out, "a") as f:
            f.write(json.dumps(row) + "\n")


if __name__ == "__main__":
    main()

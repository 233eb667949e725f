#!/usr/bin/env python3
"""Runs a benchmark matrix (scenes x view counts x variants x seeds) through `gaps train`.

Standard library only, so it runs on any machine that has the gaps binary. Every cell trains into
OUT/<cell>/ (metrics.json with the evaluation curve, renders, report.html); a cell whose metrics.json
exists is finished and skipped, so an interrupted matrix resumes where it stopped. Each finished cell adds
one row to OUT/results.jsonl (with the curve) and OUT/results.csv (without it).

  bench/harness.py --config bench/configs/llff_protocol.json --data ../shared/data --out runs/llff \
      [--jobs 4] [--gpus 0,1] [--gaps build/client/gaps] [--flag KEY=VALUE ...] [--only REGEX] [--dry-run]

A flag's value may name the cell's scene and view count as {scene} and {views}, e.g.
--flag init-ply=clouds/{scene}_{views}v_mvs.ply (the file names of `init_bench --ply_dir`).

Stopped by SIGTERM, SIGINT or SIGHUP (`timeout`, Ctrl-C, a closed terminal), the harness stops its running
cells too (each `gaps train` saves and exits; one still running --stop-grace seconds later is killed), starts
no more, and exits with 128 + the signal; a stopped cell trains again from the start on the next run.
"""
import argparse
import concurrent.futures
import csv
import itertools
import json
import os
import platform
import queue
import re
import shutil
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
CSV_FIELDS = [
    "config", "cell", "scene", "views", "variant", "seed", "status", "psnr", "ssim", "lpips",
    "num_gaussians", "max_gaussians", "peak_memory_bytes", "peak_memory_kind", "train_seconds", "generator_seconds",
    "wall_seconds", "iterations", "resolution", "init", "init_resolution", "init_points", "init_seconds",
    "init_from_cache", "commit", "device", "error",
]
# `gaps train` exits with 3 when the run diverged: metrics.json then records it (a result, not a crash).
EXIT_DIVERGED = 3
# Flags the harness sets per cell; a config may not set them.
CELL_FLAGS = {"scene", "views", "variant", "seed", "out"}
PATH_FLAGS = {"config", "gaps_config", "init_ply"}


class ConfigError(Exception):
    pass


def load_config(path):
    with open(path) as f:
        config = json.load(f)
    for key in ("scenes", "variants", "seeds"):
        if not config.get(key):
            raise ConfigError(f"{path}: '{key}' must be a non-empty list")
    config.setdefault("name", Path(path).stem)
    # Files a config names (a TrainConfig or GapsConfig JSON) are relative to the config file.
    arms = config.setdefault("arms", {})
    for label, arm in arms.items():
        if not isinstance(arm, dict) or not arm.get("variant"):
            raise ConfigError(f"{path}: arm '{label}' needs a 'variant' (vanilla, full, no-gaps, no-dropgaussian)")
        arm.setdefault("flags", {})
    for flags in all_flag_sets(config):
        for key in list(flags):
            if key.replace("-", "_") in PATH_FLAGS and not Path(str(flags[key])).is_absolute():
                flags[key] = str((Path(path).resolve().parent / str(flags[key])).resolve())
    for scene in config["scenes"]:
        if "name" not in scene or "path" not in scene:
            raise ConfigError(f"{path}: every scene needs 'name' and 'path' (relative to --data)")
        if not scene.get("views", config.get("views")):
            raise ConfigError(f"{path}: scene {scene['name']} has no view counts ('views' on the scene or the config)")
    for flags in all_flag_sets(config):
        clash = CELL_FLAGS & {k.replace("_", "-") for k in flags}
        if clash:
            raise ConfigError(f"{path}: flags {sorted(clash)} are set per cell by the harness")
    return config


def all_flag_sets(config):
    return ([config.get("flags", {})] + list(config.get("variant_flags", {}).values()) +
            [arm["flags"] for arm in config.get("arms", {}).values()])


def cell_name(scene, views, variant, seed):
    return f"{scene}_v{views}_{variant}_s{seed}"


def expand(config):
    """The matrix in a fixed order: scene, views, variant, seed."""
    cells = []
    for scene in config["scenes"]:
        for views, variant, seed in itertools.product(scene.get("views", config.get("views")), config["variants"],
                                                      config["seeds"]):
            cells.append({"scene": scene["name"], "scene_path": scene["path"], "views": views, "variant": variant,
                          "seed": seed, "cell": cell_name(scene["name"], views, variant, seed)})
    return cells


def flag_args(flags, cell):
    args = []
    for key, value in flags.items():
        value = str(value).lower() if isinstance(value, bool) else str(value)
        value = value.replace("{scene}", cell["scene"]).replace("{views}", str(cell["views"]))
        args.append(f"--{key.replace('_', '-')}={value}")
    return args


def command(config, cell, gaps, data, out, extra_flags=()):
    flags = dict(config.get("flags", {}))
    flags.update(config.get("variant_flags", {}).get(cell["variant"], {}))
    arm = config.get("arms", {}).get(cell["variant"], {})
    flags.update(arm.get("flags", {}))
    for item in extra_flags:
        key, _, value = item.partition("=")
        flags[key.lstrip("-")] = value
    cell_out = Path(out) / cell["cell"]
    # A folder without metrics.json is a cell that was stopped part way: train it again from the start.
    restart = ["--overwrite"] if cell_out.exists() else []
    return [str(gaps), "train", f"--scene={Path(data) / cell['scene_path']}", f"--views={cell['views']}",
            f"--variant={arm.get('variant', cell['variant'])}", f"--seed={cell['seed']}", f"--out={cell_out}",
            "--quiet"] + restart + flag_args(flags, cell)


def git_commit():
    # A copy of the tree without its .git (e.g. shipped to a GPU host) names its commit in GAPS_COMMIT.
    if os.environ.get("GAPS_COMMIT"):
        return os.environ["GAPS_COMMIT"]
    try:
        head = subprocess.run(["git", "-C", str(REPO), "rev-parse", "--short", "HEAD"], capture_output=True,
                              text=True, check=True).stdout.strip()
        dirty = subprocess.run(["git", "-C", str(REPO), "status", "--porcelain", "--untracked-files=no"],
                               capture_output=True, text=True, check=True).stdout.strip()
        return head + ("-dirty" if dirty else "")
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def describe_device(gpu, run_device):
    """What the cell ran on: for a run on CUDA (run_device, metrics.json's "cuda" or "cuda:N") the GPU's
    name, else the CPU model. The GPU is the harness's slot (gpu), else the one CUDA_VISIBLE_DEVICES (or the
    machine) shows the run at its ordinal."""
    if str(run_device).startswith("cuda") and shutil.which("nvidia-smi"):
        if gpu is None:
            ordinal = int(run_device.split(":", 1)[1]) if ":" in run_device else 0
            visible = [v for v in os.environ.get("CUDA_VISIBLE_DEVICES", "").split(",") if v.strip()]
            gpu = visible[ordinal].strip() if ordinal < len(visible) else str(ordinal)
        result = subprocess.run(["nvidia-smi", f"--id={gpu}", "--query-gpu=name", "--format=csv,noheader"],
                                capture_output=True, text=True)
        if result.returncode == 0 and result.stdout.strip():
            return result.stdout.strip().splitlines()[0]
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("model name"):
                    return f"{line.split(':', 1)[1].strip()} ({os.cpu_count()} threads)"
    except OSError:
        pass
    return platform.processor() or platform.machine()


def row_from_metrics(config, cell, metrics, commit, device, wall_seconds):
    peak = metrics.get("peak_memory") or {}
    row = {
        "config": config["name"], "cell": cell["cell"], "scene": cell["scene"], "views": cell["views"],
        "variant": cell["variant"], "seed": cell["seed"], "status": metrics.get("status", "ok"),
        "psnr": metrics.get("psnr"), "ssim": metrics.get("ssim"), "lpips": metrics.get("lpips"),
        "num_gaussians": metrics.get("num_gaussians"), "max_gaussians": metrics.get("max_gaussians"), "peak_memory_bytes": peak.get("bytes"),
        "peak_memory_kind": peak.get("kind"), "train_seconds": metrics.get("train_seconds"),
        "generator_seconds": metrics.get("generator_seconds"), "wall_seconds": wall_seconds,
        "iterations": metrics.get("iterations"), "resolution": metrics.get("resolution"),
        # The method that made the points (metrics.json's init_method: "auto" resolved, fallbacks taken).
        "init": metrics.get("init_method") or metrics.get("init"),
        "init_resolution": metrics.get("init_resolution") or metrics.get("resolution"),
        # The initial Gaussians and the seconds to them (metrics.json since they were recorded; None before).
        "init_points": metrics.get("init_points"), "init_seconds": metrics.get("init_seconds"),
        "init_from_cache": metrics.get("init_from_cache"),
        "commit": commit, "device": f"{metrics.get('device')}: {device}",
        "error": metrics.get("error"), "curve": metrics.get("curve", []),
    }
    return row


class Results:
    """results.jsonl and results.csv under OUT, one row per finished cell, appended as cells finish."""

    def __init__(self, out):
        self.jsonl = Path(out) / "results.jsonl"
        self.csv = Path(out) / "results.csv"
        self.lock = threading.Lock()
        self.cells = set()
        if self.jsonl.exists():
            with open(self.jsonl) as f:
                self.cells = {json.loads(line)["cell"] for line in f if line.strip()}

    def has(self, cell):
        return cell in self.cells

    def append(self, row):
        with self.lock:
            with open(self.jsonl, "a") as f:
                f.write(json.dumps(row) + "\n")
            new_csv = not self.csv.exists()
            with open(self.csv, "a", newline="") as f:
                writer = csv.DictWriter(f, fieldnames=CSV_FIELDS, extrasaction="ignore")
                if new_csv:
                    writer.writeheader()
                writer.writerow({k: "" if row.get(k) is None else row[k] for k in CSV_FIELDS})
            self.cells.add(row["cell"])


def read_metrics(out, cell):
    path = Path(out) / cell["cell"] / "metrics.json"
    if not path.exists():
        return None
    with open(path) as f:
        return json.load(f)


class Cells:
    """The running `gaps train` processes, each in its own session so that only the harness receives a
    terminal's Ctrl-C and passes it on once (a second signal would kill a run before it saves)."""

    def __init__(self, grace_seconds):
        self.lock = threading.Lock()
        self.running = set()
        self.stop_signal = None
        self.grace_seconds = grace_seconds

    def start(self, cmd, **popen_args):
        """The started process, or None once the harness is stopping."""
        with self.lock:
            if self.stop_signal is not None:
                return None
            process = subprocess.Popen(cmd, start_new_session=True, **popen_args)
            self.running.add(process)
            return process

    def finished(self, process):
        with self.lock:
            self.running.discard(process)

    def stop(self, signum, _frame=None):
        with self.lock:
            first = self.stop_signal is None
            self.stop_signal = signum
            running = list(self.running)
        for process in running:
            process.send_signal(signal.SIGTERM)
        if first:
            threading.Thread(target=self._kill_after_grace, daemon=True).start()

    def _kill_after_grace(self):
        time.sleep(self.grace_seconds)
        with self.lock:
            running = list(self.running)
        for process in running:
            process.kill()


def run_cell(config, cell, args, gpus, results, commit, log, cells):
    gpu = gpus.get() if gpus else None
    try:
        cmd = command(config, cell, args.gaps, args.data, args.out, args.flag)
        env = dict(os.environ)
        if gpu is not None:
            env["CUDA_VISIBLE_DEVICES"] = gpu
        log_dir = Path(args.out) / "logs"
        log_dir.mkdir(parents=True, exist_ok=True)
        start = time.monotonic()
        with open(log_dir / f"{cell['cell']}.log", "w") as f:
            f.write(" ".join(cmd) + "\n")
            f.flush()
            process = cells.start(cmd, stdout=f, stderr=subprocess.STDOUT, env=env)
            if process is None:
                return None
            log(f"start  {cell['cell']}" + (f" on GPU {gpu}" if gpu is not None else ""))
            code = process.wait()
            cells.finished(process)
        wall = time.monotonic() - start
        if cells.stop_signal is not None and code != 0:
            log(f"stopped {cell['cell']} (exit status {code})")
            return None
        metrics = read_metrics(args.out, cell)
        if metrics is None or code not in (0, EXIT_DIVERGED):
            log(f"FAILED {cell['cell']} (exit status {code}; see {log_dir / (cell['cell'] + '.log')})")
            return False
        device = describe_device(gpu, metrics.get("device"))
        # What only the harness knows, kept with the cell so its row can be rebuilt later.
        with open(Path(args.out) / cell["cell"] / "harness.json", "w") as f:
            json.dump({"device": device, "wall_seconds": wall, "gpu": gpu, "commit": commit}, f)
        results.append(row_from_metrics(config, cell, metrics, commit, device, wall))
        log(f"done   {cell['cell']}: {metrics.get('status')} PSNR {metrics.get('psnr')} in {wall:.0f} s")
        return True
    finally:
        if gpus:
            gpus.put(gpu)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--config", required=True, help="matrix description (JSON, see bench/README.md)")
    parser.add_argument("--data", required=True, help="root the configs' scene paths are relative to")
    parser.add_argument("--out", required=True, help="output folder: one subfolder per cell, results.{jsonl,csv}")
    parser.add_argument("--gaps", default=str(REPO / "build" / "client" / "gaps"), help="the gaps binary")
    parser.add_argument("--jobs", type=int, default=None,
                        help="cells trained at the same time (default: one per --gpus device, else 1)")
    parser.add_argument("--gpus", default="", help="comma-separated device ids, spread over the jobs "
                        "through CUDA_VISIBLE_DEVICES (default: leave it as it is)")
    parser.add_argument("--flag", action="append", default=[], metavar="KEY=VALUE",
                        help="a gaps train flag for every cell, overriding the config's (repeatable), e.g. "
                        "--flag device=cuda --flag lpips-weights=/models/vgg16_lpips_v0.1.safetensors")
    parser.add_argument("--only", default="", help="regular expression: only cells whose name matches")
    parser.add_argument("--commit", default="", help="recorded in every row (default: git HEAD of this checkout)")
    parser.add_argument("--dry-run", action="store_true", help="print the commands of the unfinished cells")
    parser.add_argument("--stop-grace", type=float, default=60.0, metavar="SECONDS",
                        help="once stopped by a signal, how long a running cell may take to save and exit before "
                        "it is killed (default 60)")
    args = parser.parse_args(argv)
    gpu_ids = [g.strip() for g in args.gpus.split(",") if g.strip()]
    if args.jobs is None:
        args.jobs = max(1, len(gpu_ids))
    if args.jobs < 1:
        parser.error("--jobs must be at least 1")
    try:
        config = load_config(args.config)
    except (OSError, ValueError, ConfigError) as e:
        parser.error(str(e))
    if not args.dry_run and not os.access(args.gaps, os.X_OK):
        parser.error(f"{args.gaps}: no gaps binary there (build it, or pass --gaps)")
    cells = [c for c in expand(config) if re.search(args.only, c["cell"])]
    Path(args.out).mkdir(parents=True, exist_ok=True)
    results = Results(args.out)
    commit = args.commit or git_commit()
    log_lock = threading.Lock()

    def log(message):
        with log_lock:
            print(f"[{time.strftime('%H:%M:%S')}] {message}", flush=True)

    pending = []
    for cell in cells:
        metrics = read_metrics(args.out, cell)
        if metrics is None:
            pending.append(cell)
        elif not results.has(cell["cell"]):  # finished before its row was written
            extra_path = Path(args.out) / cell["cell"] / "harness.json"
            extra = json.loads(extra_path.read_text()) if extra_path.exists() else {}
            results.append(row_from_metrics(config, cell, metrics, extra.get("commit", commit),
                                            extra.get("device", "unknown"), extra.get("wall_seconds")))
    log(f"{config['name']}: {len(cells)} cells, {len(cells) - len(pending)} finished, {len(pending)} to run")
    if args.dry_run:
        for cell in pending:
            print(" ".join(command(config, cell, args.gaps, args.data, args.out, args.flag)))
        return 0
    gpus = None
    if gpu_ids:
        gpus = queue.Queue()
        for slot in range(args.jobs):  # the slots of the jobs, spread round-robin over the devices
            gpus.put(gpu_ids[slot % len(gpu_ids)])
    cells = Cells(args.stop_grace)
    stop_signals = (signal.SIGTERM, signal.SIGINT, signal.SIGHUP)
    previous = {s: signal.signal(s, cells.stop) for s in stop_signals}
    try:
        with concurrent.futures.ThreadPoolExecutor(max_workers=args.jobs) as pool:
            outcomes = list(pool.map(lambda c: run_cell(config, c, args, gpus, results, commit, log, cells),
                                     pending))
    finally:
        for s, handler in previous.items():
            signal.signal(s, handler)
    failed = outcomes.count(False)
    if cells.stop_signal is not None:
        name = signal.Signals(cells.stop_signal).name
        log(f"{config['name']}: stopped by {name}: {outcomes.count(True)} cells run, {failed} failed, "
            f"{outcomes.count(None)} not finished (they train again on the next run); rows in {results.jsonl}")
        return 128 + cells.stop_signal
    log(f"{config['name']}: {len(pending) - failed} cells run, {failed} failed; rows in {results.jsonl}")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())

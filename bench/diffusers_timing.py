"""What the diffusers side benchmarks (sdxl_diffusers_bench.py, generator_diffusers_bench.py) share: timing as
the LibTorch benchmarks time (median and fastest of the runs after the warm-up, device-synchronised), the
CUDA peak reset, and the JSON line writer. Imported from the scripts' own folder (they run as
`python bench/NAME.py`)."""
import json
import time

import torch


def sync(device):
    if device.type == "cuda":
        torch.cuda.synchronize()


def time_ms(device, warmup, runs, f):
    """(median, fastest) milliseconds of `runs` calls of f after `warmup` untimed ones."""
    for _ in range(warmup):
        f()
    sync(device)
    ms = []
    for _ in range(runs):
        t0 = time.perf_counter()
        f()
        sync(device)
        ms.append((time.perf_counter() - t0) * 1000)
    ms.sort()
    return ms[len(ms) // 2], ms[0]


def reset_peak(device):
    if device.type == "cuda":
        torch.cuda.reset_peak_memory_stats()


def json_lines(path):
    """A writer of one JSON line per measurement: printed, and appended to `path` unless it is empty."""
    def emit(j):
        line = json.dumps(j)
        print(line, flush=True)
        if path:
            with open(path, "a") as f:
                f.write(line + "\n")
    return emit

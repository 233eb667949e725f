"""gsplat's rasterization() on the Gaussians and cameras that bench/rasterizer_speed_bench dumped
(--dump_dir), timed like that program: median of `--runs` calls after 3 warm-ups, each followed by
torch.cuda.synchronize(); forward, and forward + backward of sum(rgb * w) + sum(alpha * w). gsplat
renders "RGB+ED" (colour plus expected depth: 4 composited channels, as gaps composites colour and
distance), SH degree 3, eps2d 0.3 (the same low-pass dilation), both its packed and unpacked modes.
Prints one JSON line per case and mode.
    PYTHONPATH=<gsplat target> python3 bench/gsplat_compare.py --dump_dir DIR [--json FILE]
"""
import argparse
import json
import pathlib
import statistics
import time

import numpy as np
import torch


def read_ply(path):
    data = path.read_bytes()
    end = data.index(b"end_header\n") + len(b"end_header\n")
    header = data[:end].decode().splitlines()
    count = next(int(l.split()[2]) for l in header if l.startswith("element vertex"))
    names = [l.split()[2] for l in header if l.startswith("property")]
    assert all(l.split()[1] == "float" for l in header if l.startswith("property")), "expects float properties"
    table = np.frombuffer(data[end:], dtype="<f4", count=count * len(names)).reshape(count, len(names))
    col = {n: table[:, i] for i, n in enumerate(names)}
    rest = sorted((n for n in names if n.startswith("f_rest_")), key=lambda n: int(n.split("_")[-1]))
    stack = lambda keys: np.stack([col[k] for k in keys], 1)
    sh_rest = stack(rest).reshape(count, 3, len(rest) // 3).transpose(0, 2, 1)
    sh = np.concatenate([stack(["f_dc_0", "f_dc_1", "f_dc_2"])[:, None, :], sh_rest], 1)
    return {
        "means": stack(["x", "y", "z"]),
        "log_scales": stack(["scale_0", "scale_1", "scale_2"]),
        "quats": stack(["rot_0", "rot_1", "rot_2", "rot_3"]),
        "opacity_logits": col["opacity"],
        "sh": sh,
    }


def median_ms(fn, runs, warmup=3):
    for _ in range(warmup):
        fn()
    torch.cuda.synchronize()
    times = []
    for _ in range(runs):
        t0 = time.perf_counter()
        fn()
        torch.cuda.synchronize()
        times.append((time.perf_counter() - t0) * 1e3)
    return statistics.median(times)


def time_case(name, dump_dir, runs, packed):
    from gsplat import rasterization

    g = read_ply(dump_dir / f"{name}.ply")
    cam = json.loads((dump_dir / f"{name}.json").read_text())
    dev = torch.device("cuda")
    params = {k: torch.tensor(v, device=dev, requires_grad=True) for k, v in g.items()}
    K = torch.tensor([[cam["fx"], 0, cam["cx"]], [0, cam["fy"], cam["cy"]], [0, 0, 1]], device=dev)[None]
    viewmat = torch.eye(4, device=dev)[None]
    w, h = cam["width"], cam["height"]
    gen = torch.Generator(device=dev).manual_seed(2)
    w_rgb = torch.randn(h, w, 3, device=dev, generator=gen)
    w_alpha = torch.randn(h, w, device=dev, generator=gen)

    def render():
        out, alpha, _ = rasterization(
            params["means"], params["quats"], torch.exp(params["log_scales"]),
            torch.sigmoid(params["opacity_logits"]), params["sh"], viewmat, K, w, h,
            sh_degree=3, eps2d=0.3, packed=packed, render_mode="RGB+ED")
        return out[0, ..., :3], alpha[0, ..., 0]

    def forward():
        with torch.no_grad():
            render()

    def forward_backward():
        for p in params.values():
            p.grad = None
        rgb, alpha = render()
        ((rgb * w_rgb).sum() + (alpha * w_alpha).sum()).backward()

    fwd = median_ms(forward, runs)
    torch.cuda.reset_peak_memory_stats()
    fwd_bwd = median_ms(forward_backward, runs)
    return {"case": name, "renderer": "gsplat", "packed": packed, "gaussians": len(g["means"]), "width": w,
            "height": h, "runs": runs, "forward_ms": fwd, "forward_backward_ms": fwd_bwd,
            "forward_backward_peak_mib": torch.cuda.max_memory_allocated() / 2**20}


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--dump_dir", required=True, type=pathlib.Path)
    ap.add_argument("--runs", type=int, default=20)
    ap.add_argument("--json", type=pathlib.Path)
    args = ap.parse_args()
    import gsplat

    t0 = time.perf_counter()
    from gsplat.cuda._backend import _C  # triggers the JIT build on first use
    assert _C is not None, "gsplat's CUDA extension failed to build or load"
    build_s = time.perf_counter() - t0
    lines = []
    for ply in sorted(args.dump_dir.glob("*.ply")):
        for packed in (False, True):
            line = time_case(ply.stem, args.dump_dir, args.runs, packed)
            line.update({"gsplat": gsplat.__version__, "torch": torch.__version__,
                         "gpu": torch.cuda.get_device_name(0), "extension_load_s": build_s})
            lines.append(line)
            print(json.dumps(line), flush=True)
    if args.json:
        with args.json.open("a") as f:
            for line in lines:
                f.write(json.dumps(line) + "\n")


if __name__ == "__main__":
    main()

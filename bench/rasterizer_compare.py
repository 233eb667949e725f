"""The reference rasterizers on the Gaussians and cameras that bench/rasterizer_speed_bench dumped
(--dump_dir), timed like that program: median of `--runs` calls after 3 warm-ups, each followed by
torch.cuda.synchronize(); forward, and forward + backward of sum(rgb * w) + sum(alpha * w).

- gsplat (PyPI, installed by bench/gsplat_setup.sh): rasterization() with render_mode "RGB+ED" (colour
  plus expected depth: 4 composited channels, as gaps composites colour and distance), SH degree 3,
  eps2d 0.3 (the same low-pass dilation), its packed and unpacked modes.
- inria (graphdeco-inria/diff-gaussian-rasterization, from its public source, built here by JIT): the
  rasterizer of the original 3DGS code, SH degree 3; it composites colour only and returns no alpha, so its
  loss is sum(rgb * w) (it does less work than the other two). Its kernels take unit quaternions (the 3DGS
  model normalises them in PyTorch), so the renderer normalises them too.

Each line carries psnr_vs_gaps, the renderer's colour image against the one gaps rendered (dumped by the speed
bench): a renderer handed a different scene or camera shows at once (below ~40 dB); timings of such a run mean
nothing.

Prints one JSON line per case and renderer/mode.
    PYTHONPATH=<gsplat target> python3 bench/rasterizer_compare.py --dump_dir DIR --renderers gsplat
    python3 bench/rasterizer_compare.py --dump_dir DIR --renderers inria --inria_src <checkout with third_party/glm>
"""
import argparse
import json
import math
import pathlib
import statistics
import sys
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


def load_case(name, dump_dir):
    g = read_ply(dump_dir / f"{name}.ply")
    cam = json.loads((dump_dir / f"{name}.json").read_text())
    assert cam.get("viewmat") == "identity", "the dumped camera is expected at the origin, looking down +z"
    dev = torch.device("cuda")
    params = {k: torch.tensor(v, device=dev, requires_grad=True) for k, v in g.items()}
    gen = torch.Generator(device=dev).manual_seed(2)
    w, h = cam["width"], cam["height"]
    weights = (torch.randn(h, w, 3, device=dev, generator=gen), torch.randn(h, w, device=dev, generator=gen))
    return params, cam, weights


def psnr_against_gaps(render, cam, dump_dir, name):
    """PSNR of the renderer's colour image against gaps's (dumped by the speed bench): proof that both were handed
    the same scene and camera (the renderers differ by a half-pixel convention and details of SH clamping)."""
    path = dump_dir / f"{name}_rgb.f32"
    if not path.exists():
        return None
    ours = torch.from_numpy(np.fromfile(path, dtype="<f4").reshape(cam["height"], cam["width"], 3)).cuda()
    with torch.no_grad():
        theirs = render()[0].float()
    mse = torch.mean((theirs.clamp(0, 1) - ours.clamp(0, 1)) ** 2).item()
    return 10 * math.log10(1 / max(mse, 1e-12))


def time_render(render, params, weights, runs):
    """render() -> (rgb H x W x 3, alpha H x W or None)."""
    w_rgb, w_alpha = weights

    def forward():
        with torch.no_grad():
            render()

    def forward_backward():
        for p in params.values():
            p.grad = None
        rgb, alpha = render()
        loss = (rgb * w_rgb).sum()
        if alpha is not None:
            loss = loss + (alpha * w_alpha).sum()
        loss.backward()

    fwd = median_ms(forward, runs)
    torch.cuda.reset_peak_memory_stats()
    fwd_bwd = median_ms(forward_backward, runs)
    return {"forward_ms": fwd, "forward_backward_ms": fwd_bwd,
            "forward_backward_peak_mib": torch.cuda.max_memory_allocated() / 2**20}


def gsplat_renderer(packed):
    from gsplat import rasterization

    def make(params, cam):
        dev = params["means"].device
        K = torch.tensor([[cam["fx"], 0, cam["cx"]], [0, cam["fy"], cam["cy"]], [0, 0, 1]], device=dev)[None]
        viewmat = torch.eye(4, device=dev)[None]

        def render():
            out, alpha, _ = rasterization(
                params["means"], params["quats"], torch.exp(params["log_scales"]),
                torch.sigmoid(params["opacity_logits"]), params["sh"], viewmat, K, cam["width"], cam["height"],
                sh_degree=3, eps2d=0.3, packed=packed, render_mode="RGB+ED")
            return out[0, ..., :3], alpha[0, ..., 0]
        return render
    return make


def load_inria(src):
    """Builds Inria's extension by JIT from its source folder and returns its Python package."""
    from torch.utils.cpp_extension import load

    src = pathlib.Path(src).resolve()
    glm = src / "third_party" / "glm"
    assert (glm / "glm" / "glm.hpp").exists(), f"{glm} lacks glm/glm.hpp (the glm submodule)"
    # gcc 13 no longer includes <cstdint> transitively, which the 2023 sources rely on.
    flags = ["-include", "cstdint", f"-I{glm}"]
    ext = load(name="diff_gaussian_rasterization_C", verbose=False, extra_cflags=flags, extra_cuda_cflags=flags,
               sources=[str(src / p) for p in ("cuda_rasterizer/rasterizer_impl.cu", "cuda_rasterizer/forward.cu",
                                               "cuda_rasterizer/backward.cu", "rasterize_points.cu", "ext.cpp")])
    sys.modules["diff_gaussian_rasterization._C"] = ext
    sys.path.insert(0, str(src))
    import diff_gaussian_rasterization
    return diff_gaussian_rasterization


def projection_matrix(znear, zfar, tan_x, tan_y):
    """The OpenGL-style projection of the 3DGS code (graphics_utils.getProjectionMatrix)."""
    P = torch.zeros(4, 4)
    P[0, 0] = 1 / tan_x
    P[1, 1] = 1 / tan_y
    P[3, 2] = 1.0
    P[2, 2] = zfar / (zfar - znear)
    P[2, 3] = -(zfar * znear) / (zfar - znear)
    return P


def inria_renderer(module):
    def make(params, cam):
        dev = params["means"].device
        w, h = cam["width"], cam["height"]
        assert math.isclose(cam["cx"], w / 2) and math.isclose(cam["cy"], h / 2), "Inria assumes a centred camera"
        tan_x, tan_y = w / (2 * cam["fx"]), h / (2 * cam["fy"])
        view = torch.eye(4, device=dev)  # stored transposed in the 3DGS code; identity either way
        proj = (view @ projection_matrix(0.01, 100.0, tan_x, tan_y).to(dev).T).contiguous()
        settings = module.GaussianRasterizationSettings(
            image_height=h, image_width=w, tanfovx=tan_x, tanfovy=tan_y, bg=torch.zeros(3, device=dev),
            scale_modifier=1.0, viewmatrix=view, projmatrix=proj, sh_degree=3, campos=torch.zeros(3, device=dev),
            prefiltered=False, debug=False)
        rasterizer = module.GaussianRasterizer(settings)

        def render():
            means2d = torch.zeros_like(params["means"], requires_grad=True)
            color, _ = rasterizer(means3D=params["means"], means2D=means2d,
                                  opacities=torch.sigmoid(params["opacity_logits"])[:, None], shs=params["sh"],
                                  scales=torch.exp(params["log_scales"]),
                                  rotations=torch.nn.functional.normalize(params["quats"], dim=1))
            return color.permute(1, 2, 0), None
        return render
    return make


def renderers(names, inria_src):
    out = []
    for name in names:
        if name == "gsplat":
            import gsplat
            t0 = time.perf_counter()
            from gsplat.cuda._backend import _C  # triggers the JIT build on first use
            assert _C is not None, "gsplat's CUDA extension failed to build or load"
            info = {"renderer": "gsplat", "version": gsplat.__version__, "extension_load_s": time.perf_counter() - t0}
            out += [(dict(info, packed=p), gsplat_renderer(p)) for p in (False, True)]
        elif name == "inria":
            assert inria_src, "--renderers inria needs --inria_src"
            t0 = time.perf_counter()
            module = load_inria(inria_src)
            out.append(({"renderer": "inria", "extension_load_s": time.perf_counter() - t0}, inria_renderer(module)))
        else:
            raise SystemExit(f"unknown renderer {name!r} (gsplat, inria)")
    return out


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--dump_dir", required=True, type=pathlib.Path)
    ap.add_argument("--renderers", default="gsplat", help="comma-separated: gsplat, inria")
    ap.add_argument("--inria_src", help="diff-gaussian-rasterization checkout (with third_party/glm)")
    ap.add_argument("--runs", type=int, default=20)
    ap.add_argument("--json", type=pathlib.Path)
    args = ap.parse_args()
    chosen = renderers(args.renderers.split(","), args.inria_src)
    lines = []
    for ply in sorted(args.dump_dir.glob("*.ply")):
        params, cam, weights = load_case(ply.stem, args.dump_dir)
        for info, make in chosen:
            line = {"case": ply.stem, **info, "gaussians": len(params["means"]), "width": cam["width"],
                    "height": cam["height"], "runs": args.runs}
            render = make(params, cam)
            line["psnr_vs_gaps"] = psnr_against_gaps(render, cam, args.dump_dir, ply.stem)
            line.update(time_render(render, params, weights, args.runs))
            line.update({"torch": torch.__version__, "gpu": torch.cuda.get_device_name(0)})
            lines.append(line)
            print(json.dumps(line), flush=True)
    if args.json:
        with args.json.open("a") as f:
            for line in lines:
                f.write(json.dumps(line) + "\n")


if __name__ == "__main__":
    main()

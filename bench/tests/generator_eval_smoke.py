"""generator_eval_bench end to end on the real fern scene (3 views, -r 8, CPU, a short vanilla run, one test view).

Checks what the benchmark reports, not how fast: a row per iteration and arm with the setting and the metrics
against the held-out photograph; the plain render carries no gate decision; reproject's view (warped photographs)
is admitted and closer to the photograph than the render (LPIPS); the random-weight sdxl stack's output is
rejected and far from it; restore (real Real-ESRGAN weights from scripts/setup.sh) keeps the render's structure
and is admitted; the comparison strips are written.

  python3 generator_eval_smoke.py BENCH_BINARY SCENE_DIR
"""
import json
import subprocess
import sys
import tempfile
from pathlib import Path


def main():
    bench, scene = sys.argv[1], sys.argv[2]
    if not Path(scene).exists():
        print(f"skipped: scene not found at {scene}")
        return 0
    with tempfile.TemporaryDirectory() as tmp:
        out, images = Path(tmp) / "rows.jsonl", Path(tmp) / "strips"
        run = subprocess.run([bench, f"--scene={scene}", "--views=3", "--init=sparse", "--iterations=50,100",
                              "--total_iterations=100", "--max_test_views=1", "--lora_steps=0",
                              "--arms=render,reproject,restore,sdxl_random", f"--out={out}", f"--images={images}",
                              "--init_cache=none"], capture_output=True, text=True)
        assert run.returncode == 0, run.stderr[-3000:]
        rows = [json.loads(line) for line in out.read_text().splitlines()]
        strips = sorted(p.name for p in images.iterdir())
    assert [(r["iteration"], r["arm"]) for r in rows] == [
        (it, arm) for it in (50, 100) for arm in ("render", "reproject", "restore", "sdxl_random")], rows
    by = {(r["iteration"], r["arm"]): r for r in rows}
    for r in rows:
        assert (r["scene"], r["views"], r["test_views"], r["init"]) == ("fern", 3, 1, "sparse"), r
        assert len(r["per_view"]) == 1 and 0 < r["per_view"][0]["pose_distance"] < 10, r
        assert 0 < r["ssim"] <= 1 and r["psnr"] > 0, r
    for it in (50, 100):
        render, reproject = by[(it, "render")], by[(it, "reproject")]
        restore, sdxl = by[(it, "restore")], by[(it, "sdxl_random")]
        assert render["admitted"] is None and "admitted" not in render["per_view"][0], render
        assert reproject["admitted"] == 1, reproject["per_view"]
        assert restore["admitted"] == 1 and restore["per_view"][0]["structure"] > 0.6, restore["per_view"]
        assert sdxl["admitted"] == 0 and sdxl["psnr"] < render["psnr"] - 3, sdxl["per_view"]
        if render["lpips"] is not None:
            assert reproject["lpips"] < render["lpips"], (reproject["lpips"], render["lpips"])
    assert strips == ["it100_view0.png", "it50_view0.png"], strips
    print(f"generator_eval: {len(rows)} rows checked")
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""bench/service_overhead.py end to end on the real fern scene (3 views, -r 8, CPU, a short run of the method with
three diffusion phases): in process and through gaps-trainer + gaps-worker with float32 payloads in the messages
and compact payloads through shared memory.

Checks what the benchmark reports, not how fast: one row per case, each run succeeded with its phases; the
services' phases record the hand-over's stages and bytes; shared memory was used exactly where asked, and it
leaves the messages a small fraction of the float32 ones.

  python3 service_overhead_smoke.py BUILD_DIR SCENE_DIR
"""
import json
import subprocess
import sys
import tempfile
from pathlib import Path

BENCH = Path(__file__).resolve().parent.parent / "service_overhead.py"


def main():
    build, scene = sys.argv[1], sys.argv[2]
    if not Path(scene).exists():
        print(f"skipped: scene not found at {scene}")
        return 0
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "rows.jsonl"
        run = subprocess.run([sys.executable, str(BENCH), "--build", build, "--scene", scene, "--device", "cpu",
                              "--worker_device", "cpu", "--cases", "in-process,float32-socket,compact-shared",
                              "--work", str(Path(tmp) / "work"), "--out", str(out), "--no_warm_up",
                              "--run_flags", "--init", "sparse", "--iterations", "150", "--warmup-iterations", "40",
                              "--phase-interval", "40", "--n-active", "4", "--eval-every", "0"],
                             capture_output=True, text=True)
        assert run.returncode == 0, run.stdout[-3000:] + run.stderr[-3000:]
        rows = {r["case"]: r for r in map(json.loads, out.read_text().splitlines())}
    assert sorted(rows) == ["compact-shared", "float32-socket", "in-process"], rows.keys()
    for case, r in rows.items():
        assert r["succeeded"], (case, r)
        assert r["phases"] == 3 and r["phases_skipped"] == 0, (case, r)
        assert r["iterations"] == 150 and r["psnr"] > 10 and r["wall_seconds"] > 0, (case, r)
    assert rows["in-process"]["generator_counters"] == {}, rows["in-process"]
    socket, shared = rows["float32-socket"], rows["compact-shared"]
    for r in (socket, shared):
        for stage in ("client_encode", "client_send", "client_receive", "client_decode", "worker_receive",
                      "worker_decode", "worker_encode", "worker_generate", "transfer"):
            assert stage in r["generator_stage_seconds"], (stage, r["generator_stage_seconds"])
    assert socket["generator_counters"]["shared_memory"] == 0, socket["generator_counters"]
    assert "shared_memory_bytes" not in socket["generator_counters"], socket["generator_counters"]
    assert shared["generator_counters"]["shared_memory"] == 3, shared["generator_counters"]
    assert shared["generator_counters"]["shared_memory_bytes"] > 0, shared["generator_counters"]
    assert shared["generator_counters"]["request_bytes"] < 0.05 * socket["generator_counters"]["request_bytes"], (
        shared["generator_counters"], socket["generator_counters"])
    print("service_overhead smoke: ok", {c: r["wall_seconds"] for c, r in rows.items()})
    return 0


if __name__ == "__main__":
    sys.exit(main())

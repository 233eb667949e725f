"""Tests of bench/harness.py, bench/tables.py, bench/charts.py and bench/kernel_profile.py.

The harness runs against a stand-in for `gaps train` (a script writing metrics.json as the trainer does),
so resuming, concurrency, GPU assignment, divergence and crashes can be checked in seconds.
"""
import csv
import io
import json
import os
import signal
import stat
import subprocess
import sys
import tempfile
import textwrap
import time
import unittest
import unittest.mock
from contextlib import redirect_stdout
from pathlib import Path

BENCH = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(BENCH))
import charts  # noqa: E402
import harness  # noqa: E402
import init_times  # noqa: E402
import kernel_profile  # noqa: E402
import placements_bench  # noqa: E402
import tables  # noqa: E402

# Stands in for `gaps train`: PSNR from views, seed and variant; variant "no-gaps" diverges (exit 3 with a
# metrics.json saying so), "crash" fails without metrics unless ALLOW_CRASH exists; "slow" trains for two
# minutes unless SIGTERM stops it (exit 143, as gaps train after saving), "stubborn" ignores SIGTERM; every
# call is logged.
FAKE_GAPS = textwrap.dedent("""\
    #!{python}
    import json, os, signal, sys, time
    args = dict(a[2:].split("=", 1) for a in sys.argv[2:] if "=" in a)
    out = args["out"]
    log_dir = os.path.dirname(out)
    with open(os.path.join(log_dir, "calls.log"), "a") as f:
        f.write(json.dumps({{"cell": os.path.basename(out), "start": time.time(),
                             "gpu": os.environ.get("CUDA_VISIBLE_DEVICES")}}) + "\\n")
    barrier = os.path.join(log_dir, "BARRIER")
    if os.path.exists(barrier):  # wait until that many cells have started: only concurrent runs get through
        open(os.path.join(log_dir, "started_" + os.path.basename(out)), "w").close()
        need, deadline = int(open(barrier).read()), time.time() + 60
        while len([n for n in os.listdir(log_dir) if n.startswith("started_")]) < need:
            if time.time() > deadline:
                sys.exit(1)
            time.sleep(0.05)
    variant, views, seed = args["variant"], int(args["views"]), int(args["seed"])
    if variant in ("slow", "stubborn"):
        signal.signal(signal.SIGTERM, signal.SIG_IGN if variant == "stubborn" else lambda *_: sys.exit(143))
        with open(os.path.join(log_dir, "pid_" + os.path.basename(out)), "w") as f:
            f.write(str(os.getpid()))
        time.sleep(120)
    if variant == "crash" and not os.path.exists(os.path.join(log_dir, "ALLOW_CRASH")):
        sys.exit(1)
    if os.path.exists(out) and "--overwrite" not in sys.argv:  # as gaps train refuses an interrupted run's folder
        sys.exit(2)
    os.makedirs(out, exist_ok=True)
    psnr = 20 + views + 0.1 * seed + (1.0 if variant == "full" else 0.0)
    m = {{"status": "ok", "psnr": psnr, "ssim": 0.5, "lpips": None, "num_gaussians": 1000 * views,
          "train_seconds": 10.0, "generator_seconds": None if variant == "vanilla" else 2.0,
          "peak_memory": {{"kind": "cuda_allocator", "bytes": 2 ** 30}}, "iterations": 100, "resolution": 8,
          "init": args.get("init"), "init_method": "sparse" if args.get("init") == "auto" else args.get("init"),
          "init_resolution": int(args.get("init-resolution") or 8),
          "init_points": 100 * views, "init_seconds": 0.5, "init_from_cache": seed > 0,
          "device": args.get("device", "cuda"), "argv": sys.argv[1:],
          "gpu": os.environ.get("CUDA_VISIBLE_DEVICES"),
          "curve": [{{"iteration": 50, "train_seconds": 5.0, "psnr": psnr - 1, "ssim": 0.4, "lpips": None,
                      "num_gaussians": 500}},
                     {{"iteration": 100, "train_seconds": 10.0, "psnr": psnr, "ssim": 0.5, "lpips": None,
                       "num_gaussians": 1000 * views}}]}}
    if variant == "no-gaps":
        m.update(status="diverged", psnr=None, ssim=None, error="training diverged at iteration 40 (9 Gaussians): non-finite loss")
    with open(os.path.join(out, "metrics.json"), "w") as f:
        json.dump(m, f)
    sys.exit(3 if variant == "no-gaps" else 0)
    """)


class HarnessTest(unittest.TestCase):
    def setUp(self):
        self.tmp = tempfile.TemporaryDirectory()
        self.dir = Path(self.tmp.name)
        self.gaps = self.dir / "gaps"
        self.gaps.write_text(FAKE_GAPS.format(python=sys.executable))
        self.gaps.chmod(self.gaps.stat().st_mode | stat.S_IEXEC)
        self.out = self.dir / "out"
        self.config = self.dir / "matrix.json"
        self.write_config({
            "name": "unit",
            "scenes": [{"name": "fern", "path": "llff/fern"}, {"name": "bonsai", "path": "m360/bonsai", "views": [12]}],
            "views": [3],
            "variants": ["vanilla", "full", "no-gaps", "crash"],
            "seeds": [0, 1],
            "flags": {"resolution": 8, "init": "mvs", "eval_every": 50},
            "variant_flags": {"full": {"n-active": 4}},
        })

    def tearDown(self):
        self.tmp.cleanup()

    def write_config(self, config):
        self.config.write_text(json.dumps(config))

    def run_harness(self, *extra):
        with redirect_stdout(io.StringIO()) as output:
            code = harness.main(["--config", str(self.config), "--data", "/data", "--out", str(self.out),
                                 "--gaps", str(self.gaps), "--commit", "abc123"] + list(extra))
        return code, output.getvalue()

    def start_harness_process(self, *extra):
        """The harness as its own process, for the signals only a main thread can receive."""
        return subprocess.Popen(
            [sys.executable, str(BENCH / "harness.py"), "--config", str(self.config), "--data", "/data", "--out",
             str(self.out), "--gaps", str(self.gaps), "--commit", "abc123"] + list(extra),
            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)

    def wait_for_files(self, paths):
        deadline = time.monotonic() + 30
        while not all(p.exists() and p.read_text() for p in paths) and time.monotonic() < deadline:
            time.sleep(0.05)
        self.assertTrue(all(p.exists() for p in paths), paths)

    def rows(self):
        with open(self.out / "results.jsonl") as f:
            return [json.loads(line) for line in f]

    def calls(self):
        with open(self.out / "calls.log") as f:
            return [json.loads(line) for line in f]

    def test_runs_every_cell_records_rows_and_resumes(self):
        code, output = self.run_harness()
        self.assertEqual(code, 1, "crashed cells make the harness fail")
        self.assertIn("FAILED fern_v3_crash_s0", output)
        rows = {r["cell"]: r for r in self.rows()}
        # 2 scenes x 1 view count x 4 variants x 2 seeds, minus the 4 crashed cells.
        self.assertEqual(len(rows), 12)
        self.assertEqual(set(rows), {f"{s}_{v}_s{seed}" for s in ("fern_v3", "bonsai_v12")
                                     for v in ("vanilla", "full", "no-gaps") for seed in (0, 1)})
        full = rows["bonsai_v12_full_s1"]
        self.assertEqual((full["scene"], full["views"], full["variant"], full["seed"]), ("bonsai", 12, "full", 1))
        self.assertAlmostEqual(full["psnr"], 33.1)
        self.assertEqual(full["commit"], "abc123")
        self.assertEqual(full["peak_memory_bytes"], 2 ** 30)
        self.assertEqual(full["generator_seconds"], 2.0)
        self.assertEqual(len(full["curve"]), 2)
        self.assertTrue(full["device"].startswith("cuda: "))
        self.assertEqual(full["init"], "mvs")
        diverged = rows["fern_v3_no-gaps_s0"]
        self.assertEqual(diverged["status"], "diverged")
        self.assertIsNone(diverged["psnr"])
        self.assertIn("iteration 40", diverged["error"])
        # Flags: the config's, the variant's, and the cell's own.
        argv = json.loads((self.out / "fern_v3_full_s0" / "metrics.json").read_text())["argv"]
        for flag in ("--resolution=8", "--init=mvs", "--eval-every=50", "--n-active=4", "--views=3",
                     "--variant=full", "--seed=0", "--scene=/data/llff/fern", "--quiet"):
            self.assertIn(flag, argv)
        self.assertTrue((self.out / "logs" / "fern_v3_crash_s0.log").exists())
        with open(self.out / "results.csv") as f:
            csv_rows = list(csv.DictReader(f))
        self.assertEqual(len(csv_rows), 12)
        self.assertNotIn("curve", csv_rows[0])
        self.assertEqual(list(csv_rows[0]), harness.CSV_FIELDS)

        # Resume: only the crashed cells run again; nothing is recorded twice.
        first_calls = len(self.calls())
        (self.out / "ALLOW_CRASH").write_text("")
        code, _ = self.run_harness()
        self.assertEqual(code, 0)
        again = self.calls()[first_calls:]
        self.assertEqual(sorted(c["cell"] for c in again),
                         sorted(f"{s}_crash_s{seed}" for s in ("fern_v3", "bonsai_v12") for seed in (0, 1)))
        self.assertEqual(len(self.rows()), 16)
        code, _ = self.run_harness()
        self.assertEqual(len(self.calls()), first_calls + 4, "a finished matrix runs nothing")
        self.assertEqual(len(self.rows()), 16)

        # Rows lost (results files removed) are rebuilt from the cells without training again.
        before = {r["cell"]: r for r in self.rows()}
        (self.out / "results.jsonl").unlink()
        (self.out / "results.csv").unlink()
        code, _ = self.run_harness("--commit", "other")
        self.assertEqual(code, 0)
        self.assertEqual(len(self.calls()), first_calls + 4)
        rebuilt = {r["cell"]: r for r in self.rows()}
        self.assertEqual(rebuilt, before)

    def require_concurrent_starts(self, n):
        self.out.mkdir(parents=True)
        (self.out / "BARRIER").write_text(str(n))

    def test_concurrent_jobs_spread_over_gpus(self):
        self.require_concurrent_starts(2)
        code, _ = self.run_harness("--jobs", "2", "--gpus", "0,1", "--only", "vanilla|full")
        self.assertEqual(code, 0, "the first two cells did not run at the same time")
        calls = self.calls()
        self.assertEqual(len(calls), 8)
        self.assertEqual({c["gpu"] for c in calls}, {"0", "1"})
        self.assertEqual(sorted(c["gpu"] for c in calls[:2]), ["0", "1"], "two concurrent jobs shared a GPU")
        for r in self.rows():
            self.assertEqual(json.loads((self.out / r["cell"] / "metrics.json").read_text())["gpu"] in ("0", "1"), True)

    def test_one_job_per_gpu_by_default(self):
        self.require_concurrent_starts(2)
        code, _ = self.run_harness("--gpus", "3,5", "--only", "^fern_v3_vanilla")
        self.assertEqual(code, 0, "the two cells did not run at the same time")
        self.assertEqual(sorted(c["gpu"] for c in self.calls()), ["3", "5"])

    def test_rows_name_the_gpu_a_cuda_run_used_and_the_cpu_otherwise(self):
        bin_dir = self.dir / "bin"
        bin_dir.mkdir()
        smi = bin_dir / "nvidia-smi"  # names GPU N "Card N"
        smi.write_text("#!/bin/sh\necho \"Card ${1#--id=}\"\n")
        smi.chmod(smi.stat().st_mode | stat.S_IEXEC)
        env = {"PATH": f"{bin_dir}{os.pathsep}{os.environ['PATH']}", "CUDA_VISIBLE_DEVICES": "4,6"}
        with unittest.mock.patch.dict(os.environ, env):
            self.assertEqual(self.run_harness("--only", "^fern_v3_vanilla_s0$")[0], 0)
            self.assertEqual(self.run_harness("--only", "^fern_v3_vanilla_s1$", "--flag", "device=cuda:1")[0], 0)
            self.assertEqual(self.run_harness("--only", "^fern_v3_full_s0$", "--gpus", "2")[0], 0)
            self.assertEqual(self.run_harness("--only", "^fern_v3_full_s1$", "--gpus", "2", "--flag", "device=cpu")[0], 0)
        devices = {r["cell"]: r["device"] for r in self.rows()}
        self.assertEqual(devices["fern_v3_vanilla_s0"], "cuda: Card 4")
        self.assertEqual(devices["fern_v3_vanilla_s1"], "cuda:1: Card 6")
        self.assertEqual(devices["fern_v3_full_s0"], "cuda: Card 2")
        self.assertTrue(devices["fern_v3_full_s1"].startswith("cpu: ") and "Card" not in devices["fern_v3_full_s1"],
                        devices["fern_v3_full_s1"])

    def test_extra_flags_and_only(self):
        code, _ = self.run_harness("--only", "^fern_v3_vanilla_s0$", "--flag", "device=cuda", "--flag", "init=random")
        self.assertEqual(code, 0)
        self.assertEqual([c["cell"] for c in self.calls()], ["fern_v3_vanilla_s0"])
        argv = json.loads((self.out / "fern_v3_vanilla_s0" / "metrics.json").read_text())["argv"]
        self.assertIn("--device=cuda", argv)
        self.assertIn("--init=random", argv)
        self.assertNotIn("--init=mvs", argv)

    def test_flag_values_name_the_cells_scene_and_views(self):
        code, _ = self.run_harness("--only", "^(fern_v3|bonsai_v12)_vanilla_s0$", "--flag",
                                   "init-ply=/c/{scene}_{views}v_mvs.ply")
        self.assertEqual(code, 0)
        for scene, views in (("fern", 3), ("bonsai", 12)):
            argv = json.loads((self.out / f"{scene}_v{views}_vanilla_s0" / "metrics.json").read_text())["argv"]
            self.assertIn(f"--init-ply=/c/{scene}_{views}v_mvs.ply", argv)

    def test_a_cell_stopped_part_way_trains_again(self):
        (self.out / "fern_v3_vanilla_s0" / "checkpoint").mkdir(parents=True)  # an interrupted run's folder
        code, _ = self.run_harness("--only", "^fern_v3_vanilla_s[01]$")
        self.assertEqual(code, 0)
        argv = json.loads((self.out / "fern_v3_vanilla_s0" / "metrics.json").read_text())["argv"]
        self.assertIn("--overwrite", argv)
        argv = json.loads((self.out / "fern_v3_vanilla_s1" / "metrics.json").read_text())["argv"]
        self.assertNotIn("--overwrite", argv)

    def test_a_stopped_harness_stops_its_cells_and_starts_no_more(self):
        # As `timeout` or Ctrl-C stops it: no cell may go on training unseen beside the next matrix.
        self.write_config({"name": "unit", "scenes": [{"name": "fern", "path": "llff/fern"}], "views": [3],
                           "variants": ["slow", "stubborn"], "seeds": [0, 1], "flags": {}})
        process = self.start_harness_process("--jobs", "2", "--stop-grace", "1", "--only", "_s0$")
        pid_files = [self.out / "pid_fern_v3_slow_s0", self.out / "pid_fern_v3_stubborn_s0"]
        self.wait_for_files(pid_files)
        process.send_signal(signal.SIGTERM)
        output, _ = process.communicate(timeout=30)
        self.assertEqual(process.returncode, 128 + signal.SIGTERM, output)
        self.assertIn("stopped by SIGTERM: 0 cells run, 0 failed, 2 not finished", output)
        self.assertIn("stopped fern_v3_slow_s0 (exit status 143)", output)
        self.assertIn("stopped fern_v3_stubborn_s0 (exit status -9)", output)
        for pid_file in pid_files:
            with self.assertRaises(ProcessLookupError):
                os.kill(int(pid_file.read_text()), 0)
        self.assertFalse((self.out / "results.jsonl").exists() and (self.out / "results.jsonl").read_text())

    def test_cells_after_a_stop_are_not_started(self):
        self.write_config({"name": "unit", "scenes": [{"name": "fern", "path": "llff/fern"}], "views": [3],
                           "variants": ["slow"], "seeds": [0, 1, 2], "flags": {}})
        process = self.start_harness_process("--jobs", "1")
        self.wait_for_files([self.out / "pid_fern_v3_slow_s0"])
        process.send_signal(signal.SIGINT)
        output, _ = process.communicate(timeout=30)
        self.assertEqual(process.returncode, 128 + signal.SIGINT, output)
        self.assertEqual([c["cell"] for c in self.calls()], ["fern_v3_slow_s0"])
        self.assertIn("3 not finished", output)  # the stopped cell and the two never started

    def test_rows_record_the_initialisation_that_ran(self):
        code, _ = self.run_harness("--only", "^fern_v3_vanilla_s0$", "--flag", "init=auto")
        self.assertEqual(code, 0)
        self.assertEqual(self.rows()[0]["init"], "sparse")  # "auto" as resolved by the trainer
        self.assertEqual(self.rows()[0]["init_resolution"], 8)
        self.assertEqual((self.rows()[0]["init_points"], self.rows()[0]["init_seconds"]), (300, 0.5))
        self.assertIs(self.rows()[0]["init_from_cache"], False)
        with open(self.out / "results.csv") as f:
            self.assertEqual(next(csv.DictReader(f))["init_points"], "300")

    def test_arms_run_a_variant_under_their_own_label_and_flags(self):
        self.write_config({"scenes": [{"name": "fern", "path": "llff/fern"}], "views": [3],
                           "variants": ["vanilla", "full_budget4"], "seeds": [0],
                           "flags": {"resolution": 8},
                           "arms": {"full_budget4": {"variant": "full", "flags": {"gaussians-per-variation": 4}}}})
        code, _ = self.run_harness()
        self.assertEqual(code, 0)
        rows = {r["cell"]: r for r in self.rows()}
        self.assertEqual(set(rows), {"fern_v3_vanilla_s0", "fern_v3_full_budget4_s0"})
        self.assertEqual(rows["fern_v3_full_budget4_s0"]["variant"], "full_budget4")
        argv = json.loads((self.out / "fern_v3_full_budget4_s0" / "metrics.json").read_text())["argv"]
        self.assertIn("--variant=full", argv)
        self.assertIn("--gaussians-per-variation=4", argv)
        argv = json.loads((self.out / "fern_v3_vanilla_s0" / "metrics.json").read_text())["argv"]
        self.assertNotIn("--gaussians-per-variation=4", argv)
        self.write_config({"scenes": [{"name": "a", "path": "a"}], "views": [3], "variants": ["x"], "seeds": [0],
                           "arms": {"x": {"flags": {}}}})
        with self.assertRaises(harness.ConfigError):
            harness.load_config(self.config)

    def test_config_may_not_set_per_cell_flags(self):
        self.write_config({"scenes": [{"name": "a", "path": "a"}], "views": [3], "variants": ["vanilla"],
                           "seeds": [0], "flags": {"seed": 4}})
        with self.assertRaises(harness.ConfigError):
            harness.load_config(self.config)

    def test_shipped_configs_expand(self):
        sizes = {"llff_protocol": 2 * 3 * 3, "mipnerf360_protocol": 2 * 2 * 3, "ablation": 4 * 3,
                 "gaps_variants": 5 * 4 * 3, "budget_study": 5 * 3, "budget_sweep": 2 * 5,
                 "async_phases": 2 * 2 * 3, "async_phases_rest": 3 * 2 * 3}
        for name, size in sizes.items():
            config = harness.load_config(BENCH / "configs" / f"{name}.json")
            self.assertEqual(len(harness.expand(config)), size, name)

    def test_async_configs_compare_against_the_synchronous_schedule(self):
        # 250 is the default, so the `full` arm must ask for the paper's synchronous phases itself.
        for name in ("async_phases", "async_phases_rest"):
            config = harness.load_config(BENCH / "configs" / f"{name}.json")
            by_arm = {}
            for cell in harness.expand(config):
                by_arm[cell["variant"]] = harness.command(config, cell, "gaps", "data", self.out)
            self.assertIn("--async-iterations=0", by_arm["full"], name)
            self.assertIn("--async-iterations=250", by_arm["full_async250"], name)
            self.assertIn("--variant=full", by_arm["full_async250"], name)


def row(scene, views, variant, seed, psnr, ssim=0.5, lpips=None, gaussians=1000, status="ok"):
    return {"config": "paper", "cell": harness.cell_name(scene, views, variant, seed), "scene": scene,
            "views": views, "variant": variant, "seed": seed, "status": status, "psnr": psnr, "ssim": ssim,
            "lpips": lpips, "num_gaussians": gaussians, "peak_memory_bytes": 2 ** 30, "peak_memory_kind": "cuda_allocator",
            "train_seconds": 60.0, "generator_seconds": None if variant == "vanilla" else 5.0, "commit": "abc",
            "device": "cuda: H200", "error": None if status == "ok" else "diverged",
            "curve": [] if psnr is None else [
                {"iteration": 500, "train_seconds": 30.0, "psnr": psnr - 2, "num_gaussians": gaussians // 2,
                 "lpips": None if lpips is None else lpips + 0.1},
                {"iteration": 1000, "train_seconds": 60.0, "psnr": psnr, "num_gaussians": gaussians, "lpips": lpips}]}


ROWS = [
    row("fern", 3, "vanilla", 0, 20.0, lpips=0.30), row("fern", 3, "vanilla", 1, 22.0, lpips=0.32),
    row("fern", 3, "full", 0, 21.0, lpips=0.28), row("fern", 3, "full", 1, 23.5, lpips=0.26),
    row("trex", 3, "vanilla", 0, 18.0, lpips=0.40), row("trex", 3, "vanilla", 1, 18.0, lpips=0.40),
    row("trex", 3, "full", 0, 19.0, lpips=0.35), row("trex", 3, "full", 1, 19.0, lpips=0.35),
    row("fern", 6, "vanilla", 0, 24.0), row("fern", 6, "full", 0, 25.0),
    row("trex", 6, "vanilla", 0, 23.0), row("trex", 6, "full", 0, None, status="diverged"),
]


class InitTimesTest(unittest.TestCase):
    def test_cases_and_summary_lines_are_parsed(self):
        self.assertEqual(init_times.parse_cases(["llff/fern:3,9", "m/b:12"]),
                         [("llff/fern", 3), ("llff/fern", 9), ("m/b", 12)])
        with self.assertRaises(SystemExit):
            init_times.parse_cases(["llff/fern"])
        log = "init: sparse, 563 points from 3 training views\ninit: mvs, 44937 points from 3 training views, cached"
        self.assertEqual(init_times.parse_summary(log), ("mvs", 44937))
        self.assertIsNone(init_times.parse_summary("error: no such scene"))

    def test_each_case_runs_with_an_empty_cache_and_failures_are_recorded(self):
        with tempfile.TemporaryDirectory() as tmp:
            gaps = Path(tmp) / "gaps"  # "auto" resolves to mvs; "sweep" fails; every cache folder must be new
            gaps.write_text(textwrap.dedent("""\
                #!{python}
                import os, sys
                args = dict(a[2:].split("=", 1) for a in sys.argv[2:])
                if os.path.exists(args["init-cache"]):
                    sys.exit("cache exists")
                if args["init"] == "sweep":
                    sys.exit("error: sweep failed")
                print("init: " + {{"auto": "mvs"}}.get(args["init"], args["init"]) + ", " + args["views"] + "0 points from "
                      + args["views"] + " training views")
                """).format(python=sys.executable))
            gaps.chmod(gaps.stat().st_mode | stat.S_IEXEC)
            out = Path(tmp) / "rows.jsonl"
            with redirect_stdout(io.StringIO()):
                code = init_times.main(["--gaps", str(gaps), "--data", tmp, "--out", str(out),
                                        "--methods", "auto,sweep", "--cases", "llff/fern:3,9"])
            rows = [json.loads(line) for line in out.read_text().splitlines()]
        self.assertEqual(code, 1)
        self.assertEqual([(r["views"], r["method"], r["method_used"], r["points"]) for r in rows],
                         [(3, "auto", "mvs", 30), (3, "sweep", None, None), (9, "auto", "mvs", 90), (9, "sweep", None, None)])
        self.assertEqual([r.get("error") for r in rows], [None, "error: sweep failed", None, "error: sweep failed"])


class TablesTest(unittest.TestCase):
    def setUp(self):
        self.text = tables.render_all(ROWS)["paper"]

    def test_averages_are_per_seed_scene_means_with_std(self):
        # vanilla 3 views: seed 0 (20+18)/2 = 19, seed 1 (22+18)/2 = 20 -> 19.50 ± 0.71.
        self.assertIn("| vanilla | 19.50 ± 0.71 | 0.5000 ± 0.0000 | 0.3550 ± 0.0071 |", self.text)
        # full 3 views: 20 and 21.25 -> 20.62 ± 0.88; deltas of means: PSNR 20.625 - 19.5, LPIPS 0.31 - 0.355.
        self.assertIn("| full | 20.62 ± 0.88 |", self.text)
        self.assertIn("| Δ full − vanilla | +1.12 | +0.0000 | -0.0450 |", self.text)

    def test_per_scene_psnr_with_delta(self):
        self.assertIn("| fern | full | 22.25 ± 1.77 (+1.25) | 25.00 (+1.00) |", self.text)
        self.assertIn("| trex | vanilla | 18.00 ± 0.00 | 23.00 |", self.text)

    def test_unfinished_runs_are_named_and_left_out(self):
        self.assertIn("trex_v6_full_s0: diverged", self.text)
        # 6 views, full: only fern finished, so no scene average over fern and trex exists.
        self.assertIn("| trex | full | 19.00 ± 0.00 (+1.00) | n/a |", self.text)

    def test_each_view_count_averages_the_scenes_run_at_it(self):
        # A config mixing datasets: bonsai only at 12 views, fern only at 3.
        mixed = [row("fern", 3, "vanilla", 0, 20.0), row("fern", 3, "full", 0, 21.0),
                 row("bonsai", 12, "vanilla", 0, 15.0), row("bonsai", 12, "full", 0, 16.5)]
        text = tables.render_all(mixed)["paper"]
        self.assertIn("| vanilla | 20.00 | 0.5000 | n/a | 15.00 | 0.5000 | n/a |", text)
        self.assertIn("| Δ full − vanilla | +1.00 | +0.0000 | n/a | +1.50 | +0.0000 | n/a |", text)

    def test_cost_table(self):
        self.assertIn("| 3 | full | 4 | 1000 ± 0 | 1024 ± 0 (cuda_allocator) | 60.0 ± 0.0 | 5.0 ± 0.0 | cuda: H200 |", self.text)

    def test_insert_between_markers(self):
        doc = "# B\n<!-- bench-tables:paper begin -->\nold\n<!-- bench-tables:paper end -->\ntail\n"
        new = tables.insert(doc, {"paper": "T\n"})
        self.assertEqual(new, "# B\n<!-- bench-tables:paper begin -->\nT\n<!-- bench-tables:paper end -->\ntail\n")
        with self.assertRaises(KeyError):
            tables.insert("# no markers\n", {"paper": "T\n"})


class ChartsTest(unittest.TestCase):
    def test_charts_are_written_as_png_and_svg_with_an_index(self):
        with tempfile.TemporaryDirectory() as out:
            written = charts.render_all(ROWS, out, ["png", "svg"])
            charts.write_index(out, written, ["results.jsonl"])
            names = sorted(p.name for _, paths in written for p in paths)
            self.assertEqual(names, sorted([
                "paper_fern_v3_psnr_vs_time.png", "paper_fern_v3_psnr_vs_time.svg",
                "paper_fern_v6_psnr_vs_time.png", "paper_fern_v6_psnr_vs_time.svg",
                "paper_trex_v3_psnr_vs_time.png", "paper_trex_v3_psnr_vs_time.svg",
                "paper_trex_v6_psnr_vs_time.png", "paper_trex_v6_psnr_vs_time.svg",
                # LPIPS over time only where the curves have it (the 3-view rows).
                "paper_fern_v3_lpips_vs_time.png", "paper_fern_v3_lpips_vs_time.svg",
                "paper_trex_v3_lpips_vs_time.png", "paper_trex_v3_lpips_vs_time.svg",
                "paper_psnr_vs_gaussians.png", "paper_psnr_vs_gaussians.svg"]))
            for _, paths in written:
                for p in paths:
                    self.assertGreater(p.stat().st_size, 1000, p)
            self.assertTrue(Path(out, "paper_psnr_vs_gaussians.png").read_bytes().startswith(b"\x89PNG"))
            svg = Path(out, "paper_fern_v3_psnr_vs_time.svg").read_text()
            self.assertIn("<svg", svg)
            self.assertIn("vanilla", svg)
            index = Path(out, "README.md").read_text()
            self.assertIn("![paper: fern, 3 views — test PSNR over training time](paper_fern_v3_psnr_vs_time.png)", index)
            self.assertIn("![paper: fern, 3 views — test LPIPS over training time](paper_fern_v3_lpips_vs_time.png)",
                          index)
            self.assertIn("LPIPS-VGG", Path(out, "paper_fern_v3_lpips_vs_time.svg").read_text())

    def test_speed_work_charts_per_machine_scene_and_views(self):
        def run(name, build, machine, scene, variant, seconds, psnr, rc=0):
            return {"run": name, "build": build, "machine": machine, "scene": scene, "views": 3, "variant": variant,
                    "train_seconds": seconds, "psnr": psnr, "rc": rc}
        h100, h200 = "NVIDIA H100 80GB HBM3 (one card)", "NVIDIA H200 (one card)"
        rows = [run("D", "671ea76aa", h100, "llff/fern", "vanilla", 16.1, 20.7),
                run("D", "671ea76aa", h100, "llff/fern", "full", 23.1, 22.3),
                run("E", "bab53cfbb", h100, "llff/fern", "full", 20.4, 21.9),
                run("C", "5a87f8dcc", h200, "llff/fern", "full", 21.1, 22.3),
                run("X", "deadbeef0", h200, "mipnerf360/bonsai", "full", None, None, rc=1)]  # failed: no chart
        with tempfile.TemporaryDirectory() as out:
            written = charts.render_speed_work(rows, out, ["svg"])
            names = sorted(p.name for _, paths in written for p in paths)
            self.assertEqual(names, ["speed_work_h100_fern_v3_psnr_vs_time.svg",
                                     "speed_work_h200_fern_v3_psnr_vs_time.svg"])
            svg = Path(out, "speed_work_h100_fern_v3_psnr_vs_time.svg").read_text()
            self.assertIn("E bab53cf", svg)
            self.assertNotIn("5a87f8d", svg)  # another machine's run
            self.assertIn("speed work on NVIDIA H100 80GB HBM3: fern, 3 views", written[0][0])

    def test_budget_chart_only_where_budgeted_runs_exist(self):
        budgeted = [dict(row("fern", 3, "full_k2", 0, 20.5, gaussians=400), config="sweep", max_gaussians=420),
                    dict(row("fern", 3, "vanilla_k2", 0, 19.5, gaussians=400), config="sweep", max_gaussians=420)]
        with tempfile.TemporaryDirectory() as out:
            written = charts.render_all(ROWS + budgeted, out, ["svg"])
            names = sorted(p.name for _, paths in written for p in paths)
            self.assertIn("budget_fern_v3_psnr_vs_gaussians.svg", names)
            self.assertNotIn("budget_fern_v6_psnr_vs_gaussians.svg", names)  # no budgeted run there
            self.assertNotIn("budget_trex_v3_psnr_vs_gaussians.svg", names)
            svg = Path(out, "budget_fern_v3_psnr_vs_gaussians.svg").read_text()
            self.assertIn("full", svg)
        self.assertEqual(charts.base_variant("no-gaps_k3.5"), "no-gaps")

    def test_arms_get_distinct_colours_and_variants_keep_theirs(self):
        colours = charts.label_colours({"vanilla", "vanilla_k2", "full_k8", "full"})
        self.assertEqual(colours["vanilla"], charts.COLOURS["vanilla"])
        self.assertEqual(colours["full"], charts.COLOURS["full"])
        self.assertEqual(len(set(colours.values())), 4)

    def test_budget_lines_keep_to_the_budgeted_runs_initialisation(self):
        runs = [dict(row("fern", 3, "vanilla", 0, 20.0, gaussians=1000), init="mvs"),
                dict(row("fern", 3, "vanilla_k2", 0, 21.0, gaussians=300), init="mvs", max_gaussians=300),
                dict(row("fern", 3, "vanilla_sparse", 0, 17.0, gaussians=900), init="sparse"),
                dict(row("fern", 3, "vanilla_init_r4", 0, 21.5, gaussians=950), init="mvs", init_resolution=4)]
        self.assertEqual(charts.budget_points(runs), {"vanilla": [(300.0, 21.0, True), (1000.0, 20.0, False)]})
        self.assertEqual(charts.base_variant("vanilla"), "vanilla")


class KernelProfileTest(unittest.TestCase):
    HEADER = ["ID", "Kernel Name", "Grid Size", "Section Name", "Metric Name", "Metric Unit", "Metric Value",
              "Rule Name", "Rule Type", "Rule Description", "Estimated Speedup Type", "Estimated Speedup"]

    def ncu_csv(self, launches):
        out = io.StringIO()
        out.write("==PROF== Connected to process 1 (rasterizer_speed_bench)\n")
        out.write('{"case":"100k_504x378"}\n')  # the benchmark's own output, interleaved
        w = csv.writer(out, quoting=csv.QUOTE_ALL)
        w.writerow(self.HEADER)
        for launch_id, grid, duration, issued, divergence in launches:
            w.writerow([launch_id, "rasterize_backward_kernel", grid, "GPU Speed Of Light Throughput", "Duration", "ns",
                        f"{duration:,}", "", "", "", "", ""])
            w.writerow([launch_id, "rasterize_backward_kernel", grid, "Scheduler Statistics",
                        "Issued Warp Per Scheduler", "", str(issued), "", "", "", "", ""])
            w.writerow([launch_id, "rasterize_backward_kernel", grid, "WarpStateStats", "", "", "",
                        "ThreadDivergence", "OPT", "...", "local", str(divergence)])
        return out.getvalue()

    def test_the_median_launch_of_each_grid_with_its_rules(self):
        text = self.ncu_csv([(0, "(32, 24, 1)", 702144, 0.77, 22.1), (1, "(32, 24, 1)", 600000, 0.70, 20.0),
                             (2, "(32, 24, 1)", 900000, 0.80, 25.0), (3, "(63, 63, 1)", 2574656, 0.87, 31.8)])
        lines = list(kernel_profile.summarise(text))
        self.assertEqual([l["image"] for l in lines], ["100k and 300k at 504x378", "1M at 1000x1000"])
        self.assertEqual(lines[0]["launches"], 3)
        self.assertEqual(lines[0]["duration_ns"], 702144.0)  # the middle of 600000, 702144, 900000
        self.assertEqual(lines[0]["issued_warp_per_scheduler"], 0.77)
        self.assertEqual(lines[0]["rules_estimated_speedup_pct"], {"ThreadDivergence": 22.1})
        self.assertEqual(lines[1]["duration_ns"], 2574656.0)

    def test_one_block_per_tile_in_a_row_names_the_same_cases(self):
        text = self.ncu_csv([(0, "(768, 1, 1)", 538816, 0.82, 20.0), (1, "(3969, 1, 1)", 2026912, 0.89, 23.2),
                             (2, "(5, 7, 1)", 1000, 0.5, 1.0)])
        self.assertEqual([l["image"] for l in kernel_profile.summarise(text)],
                         ["100k and 300k at 504x378", "1M at 1000x1000", "?"])

    def test_a_csv_without_rows_is_refused(self):
        with self.assertRaises(SystemExit) as refused:
            list(kernel_profile.summarise("==PROF== No kernels were profiled.\n"))
        self.assertIn("no ncu rows", str(refused.exception))



class PlacementsBenchTest(unittest.TestCase):
    """Which processes each case starts, on which GPU, under which allocator caps, and the variant it submits."""

    args = unittest.mock.Mock(trainer_gib=3.0, worker_gib=17.0)
    options = {"weights": "/w/sdxl"}

    def layout(self, case):
        return placements_bench.case_layout(case, self.args, self.options)

    def test_vanilla_starts_no_worker(self):
        self.assertEqual(self.layout("vanilla"), ([], ("cuda:0", 0.0), "vanilla"))

    def test_one_card_caps_both_on_gpu_0(self):
        workers, trainer, variant = self.layout("one-card")
        self.assertEqual([(gpu, cap) for _, gpu, cap in workers], [(0, 17.0)])
        self.assertEqual((trainer, variant), (("cuda:0", 3.0), "full"))
        self.assertIn("cuda:0", workers[0][0])
        self.assertEqual(json.loads(workers[0][0][workers[0][0].index("--backend_options") + 1]), self.options)

    def test_two_gpus_both_puts_an_uncapped_sdxl_worker_on_each_gpu(self):
        workers, trainer, variant = self.layout("two-gpus-both")
        self.assertEqual([(gpu, cap) for _, gpu, cap in workers], [(1, 0.0), (0, 0.0)])
        self.assertEqual([flags[flags.index("--device") + 1] for flags, _, _ in workers], ["cuda:1", "cuda:0"])
        self.assertTrue(all(flags[flags.index("--backend") + 1] == "sdxl" for flags, _, _ in workers))
        self.assertEqual((trainer, variant), (("cuda:0", 0.0), "full"))

    def test_an_unknown_case_is_refused_naming_the_cases(self):
        with self.assertRaises(SystemExit) as refused:
            self.layout("three-gpus")
        self.assertIn("two-gpus-both", str(refused.exception))

    def test_the_breakdown_sums_the_phases_and_keeps_the_first_phases_wait(self):
        phases = [{"seconds": {"generation": 25.0, "renders": 0.1}, "generator_stages": {"adapt_scene": 21.0},
                   "generator_counters": {"img2img_batches": 2, "img2img_member_steps": 18},
                   "selection": [{"admitted": True, "strength": 0.3}, {"admitted": False, "strength": 0.5}]},
                  {"seconds": {"generation": 2.0, "renders": 0.2}, "generator_stages": {"img2img": 3.0},
                   "generator_counters": {"img2img_batches": 1}, "skipped": True, "selection": []}]
        row = placements_bench.phase_breakdown(phases)
        self.assertEqual(row["phase_seconds"], {"generation": 27.0, "renders": 0.3})
        self.assertEqual(row["generator_stage_seconds"], {"adapt_scene": 21.0, "img2img": 3.0})
        self.assertEqual(row["generator_counters"], {"img2img_batches": 3, "img2img_member_steps": 18})
        self.assertEqual(row["request_strengths"], {"count": 2, "min": 0.3, "max": 0.5, "mean": 0.4})
        self.assertEqual(row["first_phase_generation_seconds"], 25.0)
        self.assertEqual((row["phases"], row["phases_skipped"]), (2, 1))
        self.assertEqual((row["pseudo_views_admitted"], row["pseudo_views_rejected"]), (1, 1))
        self.assertIsNone(placements_bench.phase_breakdown([])["first_phase_generation_seconds"])
        self.assertIsNone(placements_bench.phase_breakdown([])["request_strengths"])

    def test_phase_summary_reads_a_run_folder_and_counts_denoising_steps(self):
        with tempfile.TemporaryDirectory() as tmp:
            run = Path(tmp)
            script = [sys.executable, str(BENCH / "phase_summary.py"), str(run)]
            missing = subprocess.run(script, capture_output=True, text=True)
            self.assertNotEqual(missing.returncode, 0)
            self.assertIn("phases.json", missing.stderr)
            (run / "phases.json").write_text(json.dumps(
                [{"selection": [{"admitted": True, "strength": 0.301}, {"admitted": True, "strength": 0.85}]}]))
            (run / "metrics.json").write_text(json.dumps({"psnr": 23.0}))
            row = json.loads(subprocess.run(script, capture_output=True, text=True, check=True).stdout)
        self.assertEqual(row["denoising_steps"], {"9": 1, "25": 1})
        self.assertEqual((row["psnr"], row["pseudo_views_admitted"]), (23.0, 2))

    def test_empty_graph_captures_are_counted_per_worker_log(self):
        with tempfile.TemporaryDirectory() as tmp:
            good, bad = Path(tmp) / "worker0.log", Path(tmp) / "worker1.log"
            good.write_text("listening on 127.0.0.1:5000\n")
            bad.write_text("[W CUDAGraph.cpp:147] Warning: The CUDA Graph is empty. This usually means ...\n" * 4)
            counts = placements_bench.empty_graph_warnings(
                {"worker": good, "worker1": bad, "worker2": Path(tmp) / "missing.log"})
        self.assertEqual(counts, {"worker": 0, "worker1": 4, "worker2": None})


if __name__ == "__main__":
    unittest.main()

"""Tests of ctest_summary.py on hand-made ctest JUnit results (the shapes ctest 3.25 writes)."""
import json
import os
import subprocess
import sys
import tempfile
import unittest

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import ctest_summary  # noqa: E402


def case(name, status, output="", skipped=False):
    mark = '<skipped message="SKIP_REGULAR_EXPRESSION_MATCHED"/>' if skipped else ""
    return (f'<testcase name="{name}" classname="{name}" time="0.1" status="{status}">{mark}'
            f"<system-out>{output}</system-out></testcase>")


def gtest_skip(test, message):
    return f"[ RUN      ] {test}\n/src/t.cpp:12: Skipped\n{message}\n[  SKIPPED ] {test} (0 ms)\n"


def junit(*cases):
    return '<?xml version="1.0" encoding="UTF-8"?><testsuite name="(empty)">' + "".join(cases) + "</testsuite>"


GPU = {"gpu_tests.Losses.CudaAgreesWithCpu", "gpu_tests.ShadeCuda.MatchesCpu", "gpu_tests.RasterizerCudaFern.Opaque"}


class Summarise(unittest.TestCase):
    def test_counts_and_names_the_gpu_tests_skipped_without_a_device(self):
        line = ctest_summary.summarise(junit(
            case("a_test.A.Passes", "run"),
            case("a_test.A.Fails", "fail"),
            case("a_test.A.NeedsData", "notrun", gtest_skip("A.NeedsData", "no data under /x"), skipped=True),
            case("gpu_tests.Losses.CudaAgreesWithCpu", "notrun",
                 gtest_skip("Losses.CudaAgreesWithCpu", "no CUDA device"), skipped=True),
            case("gpu_tests.ShadeCuda.MatchesCpu", "notrun",
                 gtest_skip("ShadeCuda.MatchesCpu", "no CUDA device"), skipped=True)), GPU)
        self.assertEqual(line, "ctest: 1 passed, 1 failed, 3 skipped "
                               "(2 GPU tests, label gpu: no CUDA device; 1 other: 1 no data under /x)")

    def test_other_skips_are_counted_by_reason(self):
        line = ctest_summary.summarise(junit(
            case("a_test.A.Fern", "notrun", gtest_skip("A.Fern", "benchmark data not found at /d"), skipped=True),
            case("a_test.A.Bonsai", "notrun", gtest_skip("A.Bonsai", "benchmark data not found at /d"), skipped=True),
            case("a_test.A.Py", "notrun", gtest_skip("A.Py", "no lpips module"), skipped=True)), GPU)
        self.assertEqual(line, "ctest: 0 passed, 0 failed, 3 skipped "
                               "(3 other: 2 benchmark data not found at /d, 1 no lpips module)")

    def test_gpu_skips_for_several_reasons_are_counted_by_reason(self):
        line = ctest_summary.summarise(junit(
            case("gpu_tests.Losses.CudaAgreesWithCpu", "notrun",
                 gtest_skip("Losses.CudaAgreesWithCpu", "no CUDA device"), skipped=True),
            case("gpu_tests.ShadeCuda.MatchesCpu", "notrun",
                 gtest_skip("ShadeCuda.MatchesCpu", "built without the CUDA kernels"), skipped=True),
            case("gpu_tests.RasterizerCudaFern.Opaque", "notrun",
                 gtest_skip("RasterizerCudaFern.Opaque", "no CUDA device"), skipped=True)), GPU)
        self.assertEqual(line, "ctest: 0 passed, 0 failed, 3 skipped "
                               "(3 GPU tests, label gpu: 2 no CUDA device, 1 built without the CUDA kernels)")

    def test_gpu_tests_that_ran_leave_no_note(self):
        line = ctest_summary.summarise(junit(case("gpu_tests.ShadeCuda.MatchesCpu", "run"),
                                             case("b_test.B.Off", "disabled"),
                                             case("b_test.B.Missing", "notrun", "Unable to find executable")), GPU)
        self.assertEqual(line, "ctest: 1 passed, 1 failed, 0 skipped")

    def test_command_line_reads_the_files_ctest_writes(self):
        with tempfile.TemporaryDirectory() as d:
            results, gpu = os.path.join(d, "results.xml"), os.path.join(d, "gpu.json")
            with open(results, "w") as f:
                f.write(junit(case("gpu_tests.ShadeCuda.MatchesCpu", "notrun",
                                   gtest_skip("ShadeCuda.MatchesCpu", "no CUDA device"), skipped=True)))
            with open(gpu, "w") as f:
                json.dump({"kind": "ctestInfo", "tests": [{"name": "gpu_tests.ShadeCuda.MatchesCpu"}]}, f)
            script = os.path.join(os.path.dirname(os.path.abspath(__file__)), "ctest_summary.py")
            out = subprocess.run([sys.executable, script, results, gpu], capture_output=True, text=True, check=True)
            self.assertEqual(out.stdout, "ctest: 0 passed, 0 failed, 1 skipped (1 GPU test, label gpu: no CUDA device)\n")
            os.remove(results)
            out = subprocess.run([sys.executable, script, results, gpu], capture_output=True, text=True, check=True)
            self.assertEqual(out.stdout, "ctest: no test results (nothing ran)\n")


if __name__ == "__main__":
    unittest.main()

// LPIPS-VGG on CUDA against PyPI's `lpips`: the random-backbone fixtures of lpips_test.cpp, and the
// set-up's real weights on fern (tests/lpips_real_weights.h), as its CPU tests do.
#include <ATen/ATen.h>
#include <ATen/core/grad_mode.h>
#include <gtest/gtest.h>
#include <nlohmann/json.hpp>

#include "gs_trainer/eval/lpips.h"
#include "tests/gpu/require_cuda.h"
#include "tests/lpips_real_weights.h"
#include "tests/lpips_test_util.h"
#include "tests/test_util.h"

namespace gaps {
namespace {

// Asks for the device before the fixture script runs: without one there is nothing to compare.
class LpipsParity : public test::PythonFixtures {
 protected:
  static void SetUpTestSuite() {
    if (at::hasCUDA()) PythonFixtures::SetUpTestSuite();
  }
  void SetUp() override {
    GAPS_REQUIRE_CUDA();
    PythonFixtures::SetUp();
  }
};

TEST_F(LpipsParity, CudaAgreesWithPython) {
  Lpips lpips = load_lpips("zip");
  lpips.to(at::Device(at::kCUDA));
  at::NoGradGuard no_grad;
  // cuDNN convolutions may run in TF32 by default (as in PyTorch), which moves the small distances
  // by ~1e-4 relative; switched off here so that the CUDA path is checked as tightly as the CPU one.
  at::Context& context = at::globalContext();
  const bool tf32 = context.allowTF32CuDNN();
  context.setAllowTF32CuDNN(false);
  for (const nlohmann::json& pair : manifest_["pairs"]) {
    at::Tensor d = lpips.distance(read_image(pair, "a").cuda(), read_image(pair, "b").cuda());
    EXPECT_TRUE(d.is_cuda());
    const double expected = pair["distance"].get<double>();
    EXPECT_NEAR(d.item<double>(), expected, 2e-5 * expected + 1e-9);
  }
  context.setAllowTF32CuDNN(tf32);
}

// The set-up's real weights: a short fern run on CUDA reports LPIPS, and our CUDA LPIPS of its renders and
// of fern's photos matches PyPI lpips (the reference runs on the CPU).
using LpipsRealWeightsCuda = test::TempDirTest;

TEST_F(LpipsRealWeightsCuda, FernRunOnCudaMatchesPypiLpips) {
  GAPS_REQUIRE_CUDA_KERNELS();
  test::check_fern_run_lpips(dir_, "cuda");
}

}  // namespace
}  // namespace gaps

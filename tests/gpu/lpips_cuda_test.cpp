// LPIPS-VGG on CUDA against PyPI's `lpips` (the fixtures of lpips_test.cpp, whose CPU parity tests
// share them).
#include <ATen/ATen.h>
#include <ATen/core/grad_mode.h>
#include <gtest/gtest.h>
#include <nlohmann/json.hpp>

#include "gs_trainer/eval/lpips.h"
#include "tests/gpu/require_cuda.h"
#include "tests/lpips_test_util.h"

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

}  // namespace
}  // namespace gaps

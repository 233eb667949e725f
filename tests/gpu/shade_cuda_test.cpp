// shade_gaussians' CUDA kernel against the CPU one (which shade_test.cpp checks against its readable
// reference): values and every gradient, for each SH degree.
#include <array>

#include <ATen/ATen.h>
#include <gtest/gtest.h>

#include "gs_trainer/raster/rasterizer.h"
#include "tests/gpu/require_cuda.h"
#include "tests/shade_test_util.h"

namespace gaps {
namespace {

using Inputs = test::ShadeInputs;

TEST(ShadeCuda, MatchesCpu) {
  GAPS_REQUIRE_CUDA_KERNELS();
  const Inputs in = test::random_shade_inputs(5000, at::kFloat, 4);
  const at::Tensor weights = at::randn({5000, 4});
  for (int degree = 0; degree <= 3; ++degree) {
    auto run = [&](const at::Device& d) {
      auto leaf = [&](const at::Tensor& t) { return t.detach().to(d).clone().requires_grad_(true); };
      Inputs x{leaf(in.means), leaf(in.dc), leaf(in.rest), in.centre};
      const at::Tensor out = shade_gaussians(x.means, x.dc, x.rest, degree, x.centre);
      (out * weights.to(d)).sum().backward();
      return std::array<at::Tensor, 4>{out.cpu(), x.means.grad().cpu(), x.dc.grad().cpu(), x.rest.grad().cpu()};
    };
    const auto cpu = run(at::kCPU), cuda = run(at::Device(at::kCUDA, 0));
    for (int k = 0; k < 4; ++k) {
      const double scale = cpu[k].abs().max().item<double>() + 1e-30;
      EXPECT_LT((cuda[k] - cpu[k]).abs().max().item<double>() / scale, 1e-5) << "degree " << degree << " output " << k;
    }
  }
}

}  // namespace
}  // namespace gaps

// GaussianAdam's fused CUDA update against the ATen one on the CPU (which trainer_test.cpp checks by hand).
#include <vector>

#include <ATen/ATen.h>
#include <gtest/gtest.h>

#include "gs_trainer/train/adam.h"
#include "tests/gpu/require_cuda.h"
#include "tests/trainer_test_util.h"

namespace gaps {
namespace {

// A few steps with random gradients. The second step leaves one tensor without a gradient and hands another a
// strided one, which the fused launch leaves to ATen's operations.
TEST(GaussianAdamCuda, MatchesCpu) {
  GAPS_REQUIRE_CUDA_KERNELS();
  at::manual_seed(5);
  GaussianModel cpu = test::tiny_model(1000);
  for (at::Tensor* p : cpu.parameters()) *p = *p + at::randn_like(*p);
  GaussianModel cuda = cpu.to(at::Device(at::kCUDA, 0));
  const std::vector<double> lrs = {0.01, 0.02, 0.03, 0.04, 0.05, 0.06};
  GaussianAdam adam_cpu(cpu, lrs, 1e-15), adam_cuda(cuda, lrs, 1e-15);
  for (int step = 0; step < 3; ++step) {
    auto cpu_params = cpu.parameters(), cuda_params = cuda.parameters();
    for (size_t k = 0; k < cpu_params.size(); ++k) {
      if (step == 1 && k == 2) continue;
      const at::Tensor g = at::randn_like(*cpu_params[k]);
      cpu_params[k]->mutable_grad() = g;
      cuda_params[k]->mutable_grad() = g.cuda();
      if (step == 1 && k == 3) {
        cuda_params[k]->mutable_grad() = at::stack({g, g}, 1).cuda().select(1, 0);
        ASSERT_FALSE(cuda_params[k]->grad().is_contiguous());
      }
    }
    adam_cpu.step();
    adam_cuda.step();
    adam_cpu.zero_grad();
    adam_cuda.zero_grad();
  }
  auto cpu_params = cpu.parameters(), cuda_params = cuda.parameters();
  for (size_t k = 0; k < cpu_params.size(); ++k)
    EXPECT_LT((cuda_params[k]->detach().cpu() - cpu_params[k]->detach()).abs().max().item<double>(), 1e-5) << k;
}

}  // namespace
}  // namespace gaps

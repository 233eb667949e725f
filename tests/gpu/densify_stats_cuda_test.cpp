// Densification's per-step statistics on CUDA (one kernel) against DensityControl's ATen operations, written out.
#include <ATen/ATen.h>
#include <gtest/gtest.h>

#include "tests/gpu/require_cuda.h"
#if defined(GAPS_CUDA_KERNELS)
#include "gs_trainer/train/cuda/densify_stats_cuda.h"
#endif

namespace gaps {
namespace {

TEST(DensifyStatsCuda, MatchesTheAtenOperations) {
  GAPS_REQUIRE_CUDA_KERNELS();
#if defined(GAPS_CUDA_KERNELS)
  at::manual_seed(9);
  const int64_t n = 5000;
  at::Tensor accum = at::rand({n}), denom = at::randint(0, 5, {n}).to(at::kFloat);
  at::Tensor max_radii = at::randint(0, 30, {n}).to(at::kInt);
  at::Tensor cuda_accum = accum.cuda(), cuda_denom = denom.cuda(), cuda_max = max_radii.cuda();
  for (int step = 0; step < 3; ++step) {
    const at::Tensor grad = at::randn({n, 2}) * 1e-3;
    const at::Tensor radii = (at::randint(-20, 40, {n}).clamp_min(0)).to(at::kInt);
    const at::Tensor visible = radii > 0;
    accum.add_(at::where(visible, at::hypot(grad.select(1, 0) * (0.5 * 504), grad.select(1, 1) * (0.5 * 378)), 0.0));
    denom.add_(visible);
    max_radii = at::maximum(max_radii, radii);
    backend::accumulate_view_gradients_cuda(grad.cuda(), radii.cuda(), 504, 378, cuda_accum, cuda_denom, cuda_max);
  }
  EXPECT_LT((cuda_accum.cpu() - accum).abs().max().item<double>(), 1e-6);
  EXPECT_TRUE(at::equal(cuda_denom.cpu(), denom));
  EXPECT_TRUE(at::equal(cuda_max.cpu(), max_radii));
#endif
}

}  // namespace
}  // namespace gaps

// The model's activations on CUDA (one kernel each way) against the ATen operations the CPU runs.
#include <ATen/ATen.h>
#include <gtest/gtest.h>

#include "tests/gpu/require_cuda.h"
#if defined(GAPS_CUDA_KERNELS)
#include "gs_trainer/model/cuda/activations_cuda.h"
#endif

namespace gaps {
namespace {

double max_difference(const at::Tensor& cuda, const at::Tensor& cpu) {
  return (cuda.cpu() - cpu).abs().max().item<double>();
}

TEST(ActivationsCuda, MatchAtenWithAndWithoutAnOpacityScale) {
  GAPS_REQUIRE_CUDA_KERNELS();
#if defined(GAPS_CUDA_KERNELS)
  at::manual_seed(12);
  const int64_t n = 3000;
  const at::Tensor log_scales = at::randn({n, 3}) - 4, logits = at::randn({n}) * 3;
  const at::Tensor scale = (at::rand({n}) > 0.3).to(at::kFloat) / 0.7;
  const at::Tensor g_scales = at::randn({n, 3}), g_opacities = at::randn({n});
  for (const bool scaled : {false, true}) {
    const at::Tensor s = scaled ? scale.cuda() : at::Tensor();
    const backend::Activations a = backend::activations_forward_cuda(log_scales.cuda(), logits.cuda(), s);
    const at::Tensor sigmoid = at::sigmoid(logits), scales = at::exp(log_scales);
    EXPECT_LT(max_difference(a.scales, scales), 1e-6 * scales.abs().max().item<double>());
    EXPECT_LT(max_difference(a.sigmoid, sigmoid), 1e-6);
    EXPECT_LT(max_difference(a.opacities, scaled ? sigmoid * scale : sigmoid), 2e-6);
    const backend::ActivationGrads g =
        backend::activations_backward_cuda(g_scales.cuda(), g_opacities.cuda(), a.scales, a.sigmoid, s);
    EXPECT_LT(max_difference(g.log_scales, g_scales * scales), 1e-6 * (g_scales * scales).abs().max().item<double>());
    EXPECT_LT(max_difference(g.logits, at::sigmoid_backward(scaled ? g_opacities * scale : g_opacities, sigmoid)),
              1e-6);
  }
  // Only one output with a gradient: the other input's gradient stays undefined.
  const backend::Activations a = backend::activations_forward_cuda(log_scales.cuda(), logits.cuda(), at::Tensor());
  const backend::ActivationGrads g =
      backend::activations_backward_cuda(at::Tensor(), g_opacities.cuda(), a.scales, a.sigmoid, at::Tensor());
  EXPECT_FALSE(g.log_scales.defined());
  EXPECT_TRUE(g.logits.defined());
#endif
}

}  // namespace
}  // namespace gaps

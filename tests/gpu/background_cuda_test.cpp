// The compositing over a background on CUDA (its kernels) against the CPU's ATen operations: image and gradients.
#include <ATen/ATen.h>
#include <gtest/gtest.h>

#include "gs_trainer/raster/rasterizer.h"
#include "tests/gpu/require_cuda.h"

namespace gaps {
namespace {

struct Composited {
  at::Tensor rgb, g_features, g_alpha;  // on the CPU
};

Composited composite(const at::Tensor& features_in, const at::Tensor& alpha_in, const at::Tensor& background,
                     const at::Tensor& g_rgb) {
  at::Tensor features = features_in.detach().clone().requires_grad_(true);
  at::Tensor alpha = alpha_in.detach().clone().requires_grad_(true);
  const at::Tensor rgb = composite_over_background(features, alpha, background);
  (rgb * g_rgb.to(rgb.device())).sum().backward();
  return {rgb.detach().cpu(), features.grad().cpu(), alpha.grad().cpu()};
}

TEST(OverBackgroundCuda, MatchesCpu) {
  GAPS_REQUIRE_CUDA_KERNELS();
  at::manual_seed(3);
  const at::Tensor features = at::rand({17, 23, 4}), alpha = at::rand({17, 23});
  const at::Tensor background = at::tensor({0.2f, 0.5f, 0.9f}), g_rgb = at::randn({17, 23, 3});
  const Composited cpu = composite(features, alpha, background, g_rgb);
  const Composited cuda = composite(features.cuda(), alpha.cuda(), background.cuda(), g_rgb);
  EXPECT_LT((cuda.rgb - cpu.rgb).abs().max().item<double>(), 1e-6);
  EXPECT_LT((cuda.g_features - cpu.g_features).abs().max().item<double>(), 1e-6);
  EXPECT_EQ(cuda.g_features.select(2, 3).abs().max().item<double>(), 0.0);
  EXPECT_LT((cuda.g_alpha - cpu.g_alpha).abs().max().item<double>(), 1e-6);
}

}  // namespace
}  // namespace gaps

// composite_over_background on the CPU: the image by its formula and the gradients against finite differences.
#include <ATen/ATen.h>
#include <gtest/gtest.h>

#include "gs_trainer/raster/rasterizer.h"

namespace gaps {
namespace {

TEST(OverBackground, ImageIsTheColourPlusTheUncoveredBackground) {
  const at::Tensor features = at::tensor({0.1, 0.2, 0.3, 7.0}, at::kDouble).view({1, 1, 4});
  const at::Tensor alpha = at::tensor({0.25}, at::kDouble).view({1, 1});
  const at::Tensor rgb = composite_over_background(features, alpha, at::tensor({1.0, 0.0, 0.5}, at::kDouble));
  EXPECT_TRUE(at::allclose(rgb.view({3}), at::tensor({0.1 + 0.75, 0.2, 0.3 + 0.375}, at::kDouble)));
}

TEST(OverBackground, GradientsMatchFiniteDifferences) {
  at::manual_seed(4);
  const at::Tensor background = at::tensor({0.3, 0.6, 0.1}, at::kDouble);
  const at::Tensor w = at::randn({3, 4, 3}, at::kDouble);
  at::Tensor features = at::rand({3, 4, 5}, at::kDouble).requires_grad_(true);
  at::Tensor alpha = at::rand({3, 4}, at::kDouble).requires_grad_(true);
  const auto loss = [&](const at::Tensor& f, const at::Tensor& a) {
    return (composite_over_background(f, a, background) * w).sum().item<double>();
  };
  (composite_over_background(features, alpha, background) * w).sum().backward();
  const double h = 1e-6;
  for (int64_t i = 0; i < features.numel(); i += 7) {
    at::Tensor plus = features.detach().clone(), minus = features.detach().clone();
    plus.view(-1)[i] += h;
    minus.view(-1)[i] -= h;
    EXPECT_NEAR(features.grad().view(-1)[i].item<double>(), (loss(plus, alpha) - loss(minus, alpha)) / (2 * h), 1e-8);
  }
  for (int64_t i = 0; i < alpha.numel(); ++i) {
    at::Tensor plus = alpha.detach().clone(), minus = alpha.detach().clone();
    plus.view(-1)[i] += h;
    minus.view(-1)[i] -= h;
    EXPECT_NEAR(alpha.grad().view(-1)[i].item<double>(), (loss(features, plus) - loss(features, minus)) / (2 * h),
                1e-8);
  }
}

}  // namespace
}  // namespace gaps

// shade_gaussians (SH colour + view distance, one fused kernel per device) against its readable reference,
// sh_to_color plus a norm in ATen operations (itself checked against finite differences in
// gaussians_test.cpp): values and every gradient in double on the CPU. The CUDA kernels against the CPU:
// gpu/shade_cuda_test.cpp.
#include <array>

#include <ATen/ATen.h>
#include <gtest/gtest.h>

#include "common/spherical_harmonics.h"
#include "gs_trainer/raster/rasterizer.h"
#include "tests/shade_test_util.h"

namespace gaps {
namespace {

using Inputs = test::ShadeInputs;
using test::random_shade_inputs;

at::Tensor reference(const Inputs& in, int degree) {
  const at::Tensor c = at::tensor({in.centre[0], in.centre[1], in.centre[2]}, in.means.options());
  const at::Tensor offsets = in.means - c;
  const at::Tensor distance = offsets.norm(2, {1}, true);
  const at::Tensor dirs = offsets / distance.clamp_min(1e-12);
  return at::cat({sh_to_color(degree, at::cat({in.dc, in.rest}, 1), dirs), distance}, 1);
}

class ShadeDegree : public ::testing::TestWithParam<int> {};

TEST_P(ShadeDegree, MatchesTheReference) {
  const int degree = GetParam();
  const Inputs in = random_shade_inputs(300, at::kDouble, 1);
  const at::Tensor got = shade_gaussians(in.means, in.dc, in.rest, degree, in.centre);
  const at::Tensor want = reference(in, degree);
  EXPECT_GT((want.narrow(1, 0, 3) == 0).sum().item<int64_t>(), 0) << "no clamped colour: the clamp is untested";
  EXPECT_LT((got - want).abs().max().item<double>(), 1e-12);
}

TEST_P(ShadeDegree, GradientsMatchTheReference) {
  const int degree = GetParam();
  Inputs in = random_shade_inputs(200, at::kDouble, 2);
  const at::Tensor weights = at::randn({200, 4}, at::kDouble);
  auto grads_of = [&](bool fused) {
    Inputs x{in.means.clone().requires_grad_(true), in.dc.clone().requires_grad_(true),
             in.rest.clone().requires_grad_(true), in.centre};
    const at::Tensor out = fused ? shade_gaussians(x.means, x.dc, x.rest, degree, x.centre) : reference(x, degree);
    (out * weights).sum().backward();
    return std::array<at::Tensor, 3>{x.means.grad(), x.dc.grad(), x.rest.grad()};
  };
  const auto got = grads_of(true), want = grads_of(false);
  const char* names[] = {"means", "sh_dc", "sh_rest"};
  for (int k = 0; k < 3; ++k) {
    const double scale = want[k].abs().max().item<double>() + 1e-300;
    EXPECT_LT((got[k] - want[k]).abs().max().item<double>() / scale, 1e-10) << names[k];
  }
  // Coefficients above the active degree get exactly zero.
  const int used = (degree + 1) * (degree + 1) - 1;
  if (used < 15) EXPECT_EQ(got[2].narrow(1, used, 15 - used).abs().max().item<double>(), 0.0);
}

INSTANTIATE_TEST_SUITE_P(Degrees, ShadeDegree, ::testing::Range(0, 4));

TEST(Shade, RejectsTooFewCoefficientsForTheDegree) {
  const Inputs in = random_shade_inputs(4, at::kDouble, 3);
  EXPECT_THROW(shade_gaussians(in.means, in.dc, in.rest.narrow(1, 0, 7), 3, in.centre), c10::Error);
  EXPECT_THROW(shade_gaussians(in.means, in.dc.squeeze(1), in.rest, 1, in.centre), c10::Error);
}

}  // namespace
}  // namespace gaps

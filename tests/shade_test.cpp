// shade_gaussians (SH colour + view distance, one fused kernel per device) against its readable reference,
// sh_to_color plus a norm in ATen operations (itself checked against finite differences in
// gaussians_test.cpp): values and every gradient in double on the CPU, and the CUDA kernels against the
// CPU (skipped without a GPU).
#include <array>

#include <ATen/ATen.h>
#include <gtest/gtest.h>

#include "common/spherical_harmonics.h"
#include "gs_trainer/raster/rasterizer.h"

namespace gaps {
namespace {

struct Inputs {
  at::Tensor means, dc, rest;
  std::array<double, 3> centre{0.3, -0.2, -1.5};
};

// Colours straddle 0 so the clamp is exercised; one Gaussian sits almost on the centre.
Inputs random_inputs(int64_t n, at::ScalarType dtype, uint64_t seed) {
  at::manual_seed(seed);
  const auto o = at::TensorOptions().dtype(dtype);
  Inputs in;
  in.means = at::randn({n, 3}, o) * 2.0;
  in.means[0] = at::tensor({0.3 + 1e-3, -0.2, -1.5}, o);
  in.dc = at::randn({n, 1, 3}, o) * 1.5;
  in.rest = at::randn({n, 15, 3}, o) * 0.4;
  return in;
}

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
  const Inputs in = random_inputs(300, at::kDouble, 1);
  const at::Tensor got = shade_gaussians(in.means, in.dc, in.rest, degree, in.centre);
  const at::Tensor want = reference(in, degree);
  EXPECT_GT((want.narrow(1, 0, 3) == 0).sum().item<int64_t>(), 0) << "no clamped colour: the clamp is untested";
  EXPECT_LT((got - want).abs().max().item<double>(), 1e-12);
}

TEST_P(ShadeDegree, GradientsMatchTheReference) {
  const int degree = GetParam();
  Inputs in = random_inputs(200, at::kDouble, 2);
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
  const Inputs in = random_inputs(4, at::kDouble, 3);
  EXPECT_THROW(shade_gaussians(in.means, in.dc, in.rest.narrow(1, 0, 7), 3, in.centre), c10::Error);
  EXPECT_THROW(shade_gaussians(in.means, in.dc.squeeze(1), in.rest, 1, in.centre), c10::Error);
}

TEST(ShadeCuda, MatchesCpu) {
#if defined(GAPS_CUDA_KERNELS)
  if (!at::hasCUDA()) GTEST_SKIP() << "needs a CUDA device";
#else
  GTEST_SKIP() << "built without the CUDA kernels";
#endif
  const Inputs in = random_inputs(5000, at::kFloat, 4);
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

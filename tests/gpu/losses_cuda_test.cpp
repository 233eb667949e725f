// The training loss on CUDA (its fused kernels) against the CPU's ATen composition (which losses_test.cpp checks
// by hand and against finite differences): value and gradient, with and without the per-pixel weight.
#include <ATen/ATen.h>
#include <gtest/gtest.h>

#include "gs_trainer/raster/losses.h"
#include "tests/gpu/require_cuda.h"
#include "tests/losses_test_util.h"

namespace gaps {
namespace {

struct LossAndGradient {
  double loss;
  at::Tensor g_pred;  // on the CPU
};

LossAndGradient loss_and_gradient(const at::Tensor& pred_in, const at::Tensor& gt, const at::Tensor& weight) {
  at::Tensor pred = pred_in.detach().clone().requires_grad_(true);
  at::Tensor loss =
      weight.defined() ? weighted_photometric_loss(pred, gt, weight, 0.2) : photometric_loss(pred, gt, 0.2);
  (loss * 3.0).backward();  // a loss gradient other than 1
  return {loss.item<double>(), pred.grad().cpu()};
}

void expect_cuda_agrees(bool weighted) {
  const at::Tensor pred = test::random_image(30, 41, 21).to(at::kFloat);
  at::Tensor gt = test::random_image(30, 41, 22).to(at::kFloat);
  gt.select(2, 1).narrow(0, 0, 5).copy_(pred.select(2, 1).narrow(0, 0, 5));  // |pred - gt|'s kink at 0
  const at::Tensor weight = weighted ? at::rand({30, 41}) : at::Tensor();
  const LossAndGradient cpu = loss_and_gradient(pred, gt, weight);
  const LossAndGradient cuda = loss_and_gradient(pred.cuda(), gt.cuda(), weighted ? weight.cuda() : at::Tensor());
  EXPECT_NEAR(cuda.loss, cpu.loss, 1e-6);
  const double scale = cpu.g_pred.abs().max().item<double>();
  EXPECT_GT(scale, 0.0);
  EXPECT_LT((cuda.g_pred - cpu.g_pred).abs().max().item<double>(), 1e-5 * scale);
}

TEST(Losses, CudaAgreesWithCpu) {
  GAPS_REQUIRE_CUDA_KERNELS();
  expect_cuda_agrees(false);
}

TEST(Losses, WeightedCudaAgreesWithCpu) {
  GAPS_REQUIRE_CUDA_KERNELS();
  expect_cuda_agrees(true);
}

TEST(Losses, CudaRejectsAWeightOfTheWrongSize) {
  GAPS_REQUIRE_CUDA_KERNELS();
  const at::Tensor pred = test::random_image(8, 9, 1).to(at::kFloat).cuda();
  EXPECT_THROW(weighted_photometric_loss(pred, pred, at::rand({8, 8}).cuda()), std::exception);
}

}  // namespace
}  // namespace gaps

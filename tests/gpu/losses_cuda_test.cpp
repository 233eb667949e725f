// The training loss on CUDA against the CPU (where losses_test.cpp checks it).
#include <ATen/ATen.h>
#include <gtest/gtest.h>

#include "gs_trainer/raster/losses.h"
#include "tests/gpu/require_cuda.h"
#include "tests/losses_test_util.h"

namespace gaps {
namespace {

TEST(Losses, CudaAgreesWithCpu) {
  GAPS_REQUIRE_CUDA();
  at::Tensor pred = test::random_image(30, 41, 21).to(at::kFloat);
  at::Tensor gt = test::random_image(30, 41, 22).to(at::kFloat);
  at::Tensor weight = at::rand({30, 41});
  const double cpu = weighted_photometric_loss(pred, gt, weight).item<double>();
  at::Tensor cuda = weighted_photometric_loss(pred.cuda(), gt.cuda(), weight.cuda());
  EXPECT_TRUE(cuda.is_cuda());
  EXPECT_NEAR(cuda.item<double>(), cpu, 1e-6);
}

}  // namespace
}  // namespace gaps

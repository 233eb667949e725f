// The fused render-statistics kernel (gaps/cuda/render_statistics.cu) against the ATen operations that define the
// statistics on the CPU (gaps/scores.cpp): colours outside [0, 1] (clamped first), grey-level edges, borders.
#include <ATen/ATen.h>
#include <gtest/gtest.h>

#include "gs_trainer/gaps/config.h"
#include "gs_trainer/gaps/scores.h"
#include "tests/gpu/require_cuda.h"

namespace gaps {
namespace {

TEST(RenderStatisticsCuda, MatchesTheCpuOperations) {
  GAPS_REQUIRE_CUDA_KERNELS();
  at::manual_seed(5);
  const int64_t b = 4, h = 29, w = 37;
  at::Tensor images = at::rand({b, h, w, 3}, at::kFloat) * 1.4 - 0.2;
  // Image 1: a checkerboard of two grey levels (every window mixes them); image 2: a flat grey (no entropy).
  const at::Tensor board =
      (at::arange(h).view({h, 1}) + at::arange(w).view({1, w})).remainder(2).to(at::kFloat).unsqueeze(2);
  images[1] = board.expand({h, w, 3}) * 0.5 + 0.25;
  images[2] = at::full({h, w, 3}, 0.4f);
  const at::Tensor alphas = at::rand({b, h, w}, at::kFloat);
  for (int bins : {16, 2, 64}) {
    GapsConfig c;
    c.entropy_bins = bins;
    const at::Tensor cpu = render_statistics(images, alphas, c);
    const at::Tensor gpu = render_statistics(images.cuda(), alphas.cuda(), c).cpu();
    ASSERT_EQ(gpu.sizes(), cpu.sizes());
    for (int64_t k = 0; k < b; ++k) {
      SCOPED_TRACE(testing::Message() << "image " << k << ", " << bins << " bins");
      EXPECT_NEAR(gpu[k][0].item<double>(), cpu[k][0].item<double>(), 1e-9);
      EXPECT_NEAR(gpu[k][1].item<double>(), cpu[k][1].item<double>(), 1e-6);
      EXPECT_NEAR(gpu[k][2].item<double>(), cpu[k][2].item<double>(), 1e-12);
      EXPECT_NEAR(gpu[k][3].item<double>(), cpu[k][3].item<double>(), 1e-9);
    }
    // The colour channels of stacked renders (rgb and depth per pixel) are read in place: the same sums.
    const at::Tensor rgbd = at::cat({images, at::rand({b, h, w, 1}, at::kFloat)}, 3).cuda();
    const at::Tensor in_place = render_statistics(rgbd.narrow(3, 0, 3), alphas.cuda(), c).cpu();
    EXPECT_TRUE(at::allclose(in_place, gpu, 1e-12, 1e-12)) << "channels read in place differ from a copy";  // atomics
    EXPECT_GT(cpu[1][1].item<double>(), 0.2) << "the checkerboard has entropy";
    EXPECT_EQ(cpu[2][1].item<double>(), 0.0);
    EXPECT_EQ(gpu[2][1].item<double>(), 0.0);
  }
}

}  // namespace
}  // namespace gaps

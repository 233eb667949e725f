// The channels-last GroupNorm kernel (diffusion_worker/sdxl/cuda/group_norm_nhwc.cu) against ATen's GroupNorm
// (and SiLU) in float32 on the same rounded inputs, and how sdxl::GroupNorm picks between them.
#include <tuple>

#include <ATen/ATen.h>
#include <gtest/gtest.h>

#include "diffusion_worker/sdxl/layers.h"
#include "tests/gpu/require_cuda.h"
#if defined(GAPS_CUDA_KERNELS)
#include "diffusion_worker/sdxl/cuda/group_norm_nhwc_cuda.h"
#endif

namespace gaps::sdxl {
namespace {

at::Tensor channels_last(const at::Tensor& t) { return t.contiguous(at::MemoryFormat::ChannelsLast); }

TEST(GroupNormNhwcCuda, MatchesAtenGroupNormAndSiluInEveryTypeAndShape) {
  GAPS_REQUIRE_CUDA_KERNELS();
#if defined(GAPS_CUDA_KERNELS)
  at::manual_seed(3);
  // (N, C, H, W, groups): the UNet's widths; channels not a multiple of a 16-byte vector (36 in half types); one
  // pixel; more pixels than one chunk holds; a batch larger than the chunk target.
  const std::vector<std::tuple<int64_t, int64_t, int64_t, int64_t, int64_t>> shapes = {
      {2, 320, 12, 16, 32}, {3, 36, 5, 7, 4}, {1, 64, 1, 1, 32}, {2, 128, 96, 64, 32}, {700, 40, 2, 3, 8}};
  for (const auto& [n, c, h, w, groups] : shapes) {
    for (const auto& [dtype, tolerance] :
         {std::pair{at::kFloat, 1e-4}, std::pair{at::kHalf, 1e-2}, std::pair{at::kBFloat16, 5e-2}}) {
      // An offset far above the spread: moments taken naively in float32 would lose the variance to cancellation.
      const at::Tensor x = channels_last((at::randn({n, c, h, w}) * 2 + 40).to(at::kCUDA, dtype));
      const at::Tensor weight = (at::rand({c}) + 0.5).to(at::kCUDA, dtype), bias = at::randn({c}).to(at::kCUDA, dtype);
      const at::Tensor reference =
          at::group_norm(x.to(at::kFloat).contiguous(), groups, weight.to(at::kFloat), bias.to(at::kFloat), 1e-5);
      for (const bool silu : {false, true}) {
        const at::Tensor y = group_norm_nhwc_cuda(x, groups, weight, bias, 1e-5, silu);
        EXPECT_EQ(y.scalar_type(), dtype);
        EXPECT_TRUE(y.is_contiguous(at::MemoryFormat::ChannelsLast));
        EXPECT_TRUE(at::equal(y, group_norm_nhwc_cuda(x, groups, weight, bias, 1e-5, silu))) << "not deterministic";
        const at::Tensor expected = silu ? at::silu(reference) : reference;
        const double error = (y.to(at::kFloat) - expected).abs().max().item<double>();
        EXPECT_LT(error, tolerance) << n << "x" << c << "x" << h << "x" << w << " in " << groups << " groups, " << dtype
                                    << (silu ? ", with SiLU" : "");
      }
    }
  }
#endif
}

TEST(GroupNormNhwcCuda, RefusesWhatItCannotNormalise) {
  GAPS_REQUIRE_CUDA_KERNELS();
#if defined(GAPS_CUDA_KERNELS)
  const at::Tensor w = at::ones({8}, at::kCUDA), b = at::zeros({8}, at::kCUDA);
  EXPECT_THROW(group_norm_nhwc_cuda(at::rand({1, 8, 4, 4}, at::kCUDA), 2, w, b, 1e-5, false), c10::Error)
      << "an NCHW tensor";
  EXPECT_THROW(group_norm_nhwc_cuda(channels_last(at::rand({1, 8, 4, 4}, at::kCUDA)), 3, w, b, 1e-5, false), c10::Error)
      << "8 channels in 3 groups";
  EXPECT_THROW(
      group_norm_nhwc_cuda(channels_last(at::rand({1, 8, 4, 4}, at::kCUDA)), 2, w.slice(0, 0, 4), b, 1e-5, false),
      c10::Error)
      << "a weight of 4 values";
  const at::Tensor wide = channels_last(at::rand({1, 8192, 2, 2}, at::kCUDA));
  EXPECT_THROW(group_norm_nhwc_cuda(wide, 32, at::ones({8192}, at::kCUDA), at::zeros({8192}, at::kCUDA), 1e-5, false),
               c10::Error)
      << "8192 channels";
#endif
}

// sdxl::GroupNorm keeps channels-last activations channels-last through the kernel when nothing records a graph,
// and takes ATen's (which autograd differentiates) when something does.
TEST(GroupNormNhwcCuda, TheLayerTakesTheKernelOnlyOutsideAutograd) {
  GAPS_REQUIRE_CUDA_KERNELS();
  const GroupNorm norm{at::rand({64}, at::kCUDA) + 0.5, at::randn({64}, at::kCUDA), 32, 1e-5};
  const at::Tensor x = channels_last(at::randn({2, 64, 6, 5}, at::kCUDA));
  const at::Tensor fused = norm.with_silu(x);
  EXPECT_TRUE(fused.is_contiguous(at::MemoryFormat::ChannelsLast) && !fused.is_contiguous());
  const at::Tensor leaf = x.clone().requires_grad_(true);
  const at::Tensor recorded = norm.with_silu(leaf);
  EXPECT_TRUE(recorded.requires_grad());
  recorded.sum().backward();
  ASSERT_TRUE(leaf.grad().defined());
  EXPECT_LT((recorded.detach() - fused).abs().max().item<double>(), 1e-4);
  // NCHW activations take ATen's whatever the mode, unless the layer belongs to a channels-last model.
  EXPECT_TRUE(norm(x.contiguous()).is_contiguous());
  GroupNorm of_channels_last_model = norm;
  of_channels_last_model.channels_last = true;
  const at::Tensor converted = of_channels_last_model.with_silu(x.contiguous());
  EXPECT_TRUE(converted.is_contiguous(at::MemoryFormat::ChannelsLast) && !converted.is_contiguous());
  EXPECT_TRUE(at::equal(converted, fused));
}

}  // namespace
}  // namespace gaps::sdxl

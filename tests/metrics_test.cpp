// Evaluation metrics: PSNR and SSIM values, clamping, and the per-view averaging helper.
// (LPIPS through evaluate_image is covered in lpips_test.cpp, which has a backbone to load.)
#include "gs_trainer/eval/metrics.h"

#include <ATen/ATen.h>
#include <gtest/gtest.h>

#include <cmath>
#include <limits>

#include "gs_trainer/raster/losses.h"

namespace gaps {
namespace {

at::Tensor random_image(int64_t h, int64_t w, uint64_t seed) {
  at::Generator gen = at::make_generator<at::CPUGeneratorImpl>(seed);
  return at::rand({h, w, 3}, gen, at::TensorOptions().dtype(at::kFloat));
}

TEST(Psnr, KnownMseGivesKnownValue) {
  // MSE 0.01 -> 20 dB; MSE 1e-4 -> 40 dB.
  EXPECT_NEAR(psnr(at::full({4, 5, 3}, 0.5), at::full({4, 5, 3}, 0.6)), 20.0, 1e-5);
  EXPECT_NEAR(psnr(at::full({4, 5, 3}, 0.25), at::full({4, 5, 3}, 0.26)), 40.0, 1e-4);
}

TEST(Psnr, AveragesSquaredErrorOverPixelsAndChannels) {
  at::Tensor pred = random_image(9, 11, 1);
  at::Tensor gt = random_image(9, 11, 2);
  auto p = pred.accessor<float, 3>();
  auto g = gt.accessor<float, 3>();
  double sum = 0;
  for (int y = 0; y < 9; ++y)
    for (int x = 0; x < 11; ++x)
      for (int c = 0; c < 3; ++c) {
        const double d = double(p[y][x][c]) - double(g[y][x][c]);
        sum += d * d;
      }
  EXPECT_NEAR(psnr(pred, gt), 10 * std::log10(9 * 11 * 3 / sum), 1e-9);
}

TEST(Psnr, IdenticalImagesAreInfinite) {
  at::Tensor image = random_image(6, 7, 3);
  EXPECT_EQ(psnr(image, image.clone()), std::numeric_limits<double>::infinity());
}

TEST(Psnr, ClampsToUnitRange) {
  at::Tensor gt = random_image(6, 7, 4);
  // Overshoot beyond [0, 1] where gt is at the bounds costs nothing after clamping.
  at::Tensor gt_bounds = (gt > 0.5).to(at::kFloat);
  at::Tensor overshoot = gt_bounds * 1.7 - (1 - gt_bounds) * 0.3;
  EXPECT_EQ(psnr(overshoot, gt_bounds), std::numeric_limits<double>::infinity());
  at::Tensor pred = gt + 0.5 * (random_image(6, 7, 5) - 0.5);
  EXPECT_NEAR(psnr(pred, gt), psnr(pred.clamp(0, 1), gt), 1e-12);
  EXPECT_NE(psnr(pred, gt), 10 * std::log10(1.0 / (pred - gt).pow(2).mean().item<double>()));
}

TEST(SsimMetric, EqualsTrainingSsimOnClampedImages) {
  at::Tensor gt = random_image(24, 20, 6);
  at::Tensor pred = 0.7 * gt + 0.3 * random_image(24, 20, 7);
  EXPECT_NEAR(ssim_metric(pred, gt), gaps::ssim(pred, gt).item<double>(), 1e-7);
  at::Tensor out_of_range = pred * 1.6 - 0.3;
  EXPECT_NEAR(ssim_metric(out_of_range, gt), gaps::ssim(out_of_range.clamp(0, 1), gt).item<double>(), 1e-7);
  EXPECT_NE(ssim_metric(out_of_range, gt), gaps::ssim(out_of_range, gt).item<double>());
}

TEST(EvaluateImage, ComputesPsnrAndSsimWithoutLpips) {
  at::Tensor gt = random_image(24, 20, 8);
  // A render that still requires grad: evaluation must not build graphs or fail on it.
  at::Tensor pred = (0.8 * gt + 0.2 * random_image(24, 20, 9)).requires_grad_(true);
  ImageMetrics m = evaluate_image(pred, gt);
  EXPECT_DOUBLE_EQ(m.psnr, psnr(pred, gt));
  EXPECT_DOUBLE_EQ(m.ssim, ssim_metric(pred, gt));
  EXPECT_FALSE(m.lpips.has_value());
  EXPECT_GT(m.psnr, 10.0);
  EXPECT_LT(m.ssim, 1.0);
}

TEST(AverageMetrics, AveragesPerView) {
  auto mean = average_metrics({{20.0, 0.5, 0.3}, {30.0, 0.7, 0.1}, {25.0, 0.9, 0.2}});
  ASSERT_TRUE(mean.ok()) << mean.status();
  EXPECT_DOUBLE_EQ(mean->psnr, 25.0);
  EXPECT_DOUBLE_EQ(mean->ssim, 0.7);
  ASSERT_TRUE(mean->lpips.has_value());
  EXPECT_NEAR(*mean->lpips, 0.2, 1e-15);
}

TEST(AverageMetrics, LpipsStaysAbsentWhenNoViewHasIt) {
  auto mean = average_metrics({{20.0, 0.5, std::nullopt}, {22.0, 0.6, std::nullopt}});
  ASSERT_TRUE(mean.ok()) << mean.status();
  EXPECT_DOUBLE_EQ(mean->psnr, 21.0);
  EXPECT_FALSE(mean->lpips.has_value());
}

TEST(AverageMetrics, RejectsEmptyAndMixedInput) {
  EXPECT_EQ(average_metrics({}).status().code(), absl::StatusCode::kInvalidArgument);
  auto mixed = average_metrics({{20.0, 0.5, 0.1}, {21.0, 0.5, 0.1}, {22.0, 0.6, std::nullopt}});
  EXPECT_EQ(mixed.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_NE(mixed.status().message().find("view 2"), absl::string_view::npos) << mixed.status();
}

}  // namespace
}  // namespace gaps

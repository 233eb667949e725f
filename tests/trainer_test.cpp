// Optimiser, schedules, adaptive density control and configuration of the vanilla trainer. The fused CUDA
// optimiser step against this one: gpu/adam_cuda_test.cpp.
#include <cmath>

#include <ATen/ATen.h>
#include <ATen/core/grad_mode.h>
#include <gtest/gtest.h>
#include <nlohmann/json.hpp>

#include "gs_trainer/model/render.h"
#include "gs_trainer/scene/camera.h"
#include "gs_trainer/train/adam.h"
#include "gs_trainer/train/densify.h"
#include "gs_trainer/train/train_config.h"
#include "gs_trainer/train/trainer.h"
#include "tests/trainer_test_util.h"

namespace gaps {
namespace {

using test::tiny_model;

void set_grads(GaussianModel& m, double value) {
  for (at::Tensor* p : m.parameters()) p->mutable_grad() = at::full_like(*p, value);
}

TEST(GaussianAdam, FirstStepsMatchHandComputedAdam) {
  GaussianModel m = tiny_model(2);
  GaussianAdam adam(m, {0.1, 0.1, 0.1, 0.1, 0.1, 0.1}, 1e-15);
  const double x0 = m.means[0][0].item<double>();
  // Step 1 with gradient g: m = 0.1 g, v = 0.001 g^2, bias-corrected update = lr * g / |g| = lr.
  set_grads(m, 2.0);
  adam.step();
  EXPECT_NEAR(m.means[0][0].item<double>(), x0 - 0.1, 1e-6);
  // Step 2 with gradient -2: m = 0.09*2 - 0.2 = -0.02; v = 0.999*0.004 + 0.004 = 0.007996.
  set_grads(m, -2.0);
  adam.step();
  const double mh = -0.02 / (1 - 0.81), vh = 0.007996 / (1 - 0.998001);
  EXPECT_NEAR(m.means[0][0].item<double>(), x0 - 0.1 - 0.1 * mh / std::sqrt(vh), 1e-6);
}

TEST(GaussianAdam, StateFollowsRowsThroughKeepAndAppend) {
  GaussianModel m = tiny_model(3);
  GaussianAdam adam(m, {0.1, 0.1, 0.1, 0.1, 0.1, 0.1}, 1e-15);
  set_grads(m, 1.0);
  adam.step();
  adam.keep_rows(at::tensor({1, 0, 1}).to(at::kBool));
  EXPECT_EQ(m.size(), 2);
  EXPECT_TRUE(m.means.requires_grad());
  adam.append_rows(tiny_model(4));
  EXPECT_EQ(m.size(), 6);
  EXPECT_EQ(m.sh_rest.size(0), 6);
  // Old rows keep momentum (move again without gradient in step 2's direction); new rows start at rest.
  const auto before = m.means.detach().clone();
  for (at::Tensor* p : m.parameters()) p->mutable_grad() = at::zeros_like(*p);
  adam.step();
  EXPECT_GT((m.means[0] - before[0]).abs().sum().item<double>(), 0.0);
  EXPECT_EQ((m.means[4] - before[4]).abs().sum().item<double>(), 0.0);
}

TEST(ExponentialLr, InterpolatesLogLinearlyAndClamps) {
  EXPECT_DOUBLE_EQ(exponential_lr(0, 1e-2, 1e-4, 100), 1e-2);
  EXPECT_NEAR(exponential_lr(50, 1e-2, 1e-4, 100), 1e-3, 1e-12);
  EXPECT_NEAR(exponential_lr(100, 1e-2, 1e-4, 100), 1e-4, 1e-15);
  EXPECT_NEAR(exponential_lr(500, 1e-2, 1e-4, 100), 1e-4, 1e-15);
}

struct DensifyFixture : ::testing::Test {
  TrainConfig config;
  GaussianModel model = tiny_model(4);
  void SetUp() override {
    config.densify_grad_threshold = 0.0002;
    config.percent_dense = 0.01;
    config.opacity_reset_interval = 3000;
    // Gaussian 0 small with high gradient (clone), 1 large with high gradient (split), 2 low gradient,
    // 3 nearly transparent (pruned).
    model.log_scales[1].fill_(std::log(0.5));
    model.opacity_logits[3] = std::log(0.001 / 0.999);
  }
};

TEST_F(DensifyFixture, ClonesSmallSplitsLargePrunesTransparent) {
  GaussianAdam adam(model, {0.1, 0.1, 0.1, 0.1, 0.1, 0.1}, 1e-15);
  DensityControl density(config, /*scene_extent=*/1.0);
  // Pixel-space gradients; scaled by (W/2, H/2) = (50, 50) they give NDC norms 0.001, 0.001, 0.00001, 0.
  const auto g = at::tensor({2e-5f, 0.f, 2e-5f, 0.f, 2e-7f, 0.f, 0.f, 0.f}).view({4, 2});
  density.accumulate(g, at::Tensor(), at::full({4}, 3, at::kInt), 100, 100);
  const auto means_before = model.means.detach().clone();
  const int64_t n = density.densify_and_prune(model, adam, 600, 0);
  // 4 - 1 split parent + 1 clone + 2 split children - 1 pruned = 5
  EXPECT_EQ(n, 5);
  at::AutoGradMode no_grad(false);
  const auto scales = at::exp(model.log_scales).amax(1);
  // Two Gaussians at the clone's original position and scale (original + clone).
  const auto at_clone = (model.means - means_before[0]).norm(2, {1}) < 1e-6;
  EXPECT_EQ(at_clone.sum().item<int64_t>(), 2);
  // The split children are 1.6x smaller than the parent.
  EXPECT_EQ((at::abs(scales - 0.5 / 1.6) < 1e-5).sum().item<int64_t>(), 2);
  EXPECT_EQ((at::abs(scales - 0.5) < 1e-5).sum().item<int64_t>(), 0);
  EXPECT_TRUE((model.opacities() > 0.005).all().item<bool>());
}

TEST_F(DensifyFixture, LargeScreenFootprintsArePrunedOnlyAfterTheFirstReset) {
  GaussianAdam adam(model, {0.1, 0.1, 0.1, 0.1, 0.1, 0.1}, 1e-15);
  DensityControl density(config, 100.0);
  const auto radii = at::tensor({5, 50, 5, 5}, at::kInt);
  density.accumulate(at::zeros({4, 2}), at::Tensor(), radii, 100, 100);
  EXPECT_EQ(density.densify_and_prune(model, adam, 600, 0), 3);  // only the transparent one
  density.accumulate(at::zeros({3, 2}), at::Tensor(), at::tensor({5, 50, 5}, at::kInt), 100, 100);
  EXPECT_EQ(density.densify_and_prune(model, adam, 3100, 0), 2);  // now the 50-pixel one too
}

TEST_F(DensifyFixture, LargeScreenFootprintsAreKeptWithoutOpacityResets) {
  config.opacity_reset_interval = 0;
  GaussianAdam adam(model, {0.1, 0.1, 0.1, 0.1, 0.1, 0.1}, 1e-15);
  DensityControl density(config, 1.0);
  density.accumulate(at::zeros({4, 2}), at::Tensor(), at::tensor({5, 50, 5, 5}, at::kInt), 100, 100);
  EXPECT_EQ(density.densify_and_prune(model, adam, 3100, 0), 3);  // only the transparent one
}

TEST_F(DensifyFixture, OpacityResetCapsAtOnePercent) {
  GaussianAdam adam(model, {0.1, 0.1, 0.1, 0.1, 0.1, 0.1}, 1e-15);
  DensityControl::reset_opacity(model, adam);
  EXPECT_NEAR(model.opacities().max().item<double>(), 0.01, 1e-6);
  EXPECT_NEAR(model.opacities()[3].item<double>(), 0.001, 1e-6);
}

TEST_F(DensifyFixture, GrowthStopsAtTheGaussianBudget) {
  config.max_gaussians = 4;
  GaussianAdam adam(model, {0.1, 0.1, 0.1, 0.1, 0.1, 0.1}, 1e-15);
  DensityControl density(config, 1.0);
  density.accumulate(at::full({4, 2}, 1e-3f), at::Tensor(), at::full({4}, 3, at::kInt), 100, 100);
  EXPECT_EQ(density.densify_and_prune(model, adam, 600, 0), 3);  // prune only, no growth
}

// With room for one more Gaussian, the candidate with the larger gradient (the small one, cloned) grows and
// the other (the large one) is not split.
TEST_F(DensifyFixture, GrowthStopsExactlyAtTheBudgetPreferringLargerGradients) {
  config.max_gaussians = 5;
  GaussianAdam adam(model, {0.1, 0.1, 0.1, 0.1, 0.1, 0.1}, 1e-15);
  DensityControl density(config, 1.0);
  const auto g = at::tensor({3e-5f, 0.f, 2e-5f, 0.f, 2e-7f, 0.f, 0.f, 0.f}).view({4, 2});
  density.accumulate(g, at::Tensor(), at::full({4}, 3, at::kInt), 100, 100);
  const auto means_before = model.means.detach().clone();
  // 4 + 1 clone = 5 (the budget), then the transparent one is pruned.
  EXPECT_EQ(density.densify_and_prune(model, adam, 600, 0), 4);
  at::AutoGradMode no_grad(false);
  EXPECT_EQ(((model.means - means_before[0]).norm(2, {1}) < 1e-6).sum().item<int64_t>(), 2);      // cloned
  EXPECT_EQ((at::abs(at::exp(model.log_scales).amax(1) - 0.5) < 1e-5).sum().item<int64_t>(), 1);  // not split
}

// A 16 x 12 view of 8 small Gaussians in front of it (and `extra` more far outside it), for schedule tests.
struct ScheduleScene {
  GaussianModel model;
  Camera camera;
  explicit ScheduleScene(int outside = 0) {
    model = tiny_model(8 + outside);
    model.means.select(1, 2).add_(2.0);  // in front of the camera
    for (int i = 0; i < outside; ++i) model.means[8 + i][0] = 100.0 + i;
    model.opacity_logits.fill_(0.0);  // opacity 0.5
    camera.width = 16;
    camera.height = 12;
    camera.fx = camera.fy = 20;
    camera.cx = 8;
    camera.cy = 6;
  }
  Trainer trainer(const TrainConfig& config) const {
    return Trainer(model, {TrainingView{camera, at::full({12, 16, 3}, 0.5f)}}, config);
  }
};

TrainConfig schedule_config() {
  TrainConfig config;
  config.iterations = 100;
  config.densify_from_iter = 1000;  // no densification: only the schedule under test acts
  config.densify_until_fraction = 1.0;
  return config;
}

// With opacity_reset_interval N every N-th iteration of the densification window caps the opacities at 1%;
// the default (0) never resets them.
double max_opacity_after(int iterations, int reset_interval) {
  TrainConfig config = schedule_config();
  config.opacity_reset_interval = reset_interval;
  Trainer trainer = ScheduleScene().trainer(config);
  for (int i = 0; i < iterations; ++i) trainer.step();
  at::AutoGradMode no_grad(false);
  return trainer.model().opacities().max().item<double>();
}

TEST(TrainerSchedule, OpacityResetOnlyWhenAskedFor) {
  EXPECT_EQ(TrainConfig{}.opacity_reset_interval, 0);
  EXPECT_GT(max_opacity_after(10, 0), 0.3);
  EXPECT_GT(max_opacity_after(9, 10), 0.3);
  // Reset at iteration 10, then one Adam step of at most lr = 0.05 in logit space.
  EXPECT_LT(max_opacity_after(10, 10), 0.0106);
}

// The active SH degree: a model made from points starts at 0 and rises every sh_increase_interval iterations;
// a loaded model that already renders at degree 1 keeps it (continuing it must not drop its view-dependent
// colour).
TEST(TrainerSchedule, ShDegreeStartsWhereTheModelIs) {
  TrainConfig config = schedule_config();
  config.sh_increase_interval = 3;
  ScheduleScene fresh;
  Trainer from_points = fresh.trainer(config);
  from_points.step();
  EXPECT_EQ(from_points.model().sh_degree, 0);
  for (int i = 0; i < 2; ++i) from_points.step();
  EXPECT_EQ(from_points.model().sh_degree, 1);

  ScheduleScene loaded;
  loaded.model.sh_degree = 1;
  Trainer continued = loaded.trainer(config);
  continued.step();
  EXPECT_EQ(continued.model().sh_degree, 1);
  loaded.model.sh_degree = 7;  // above the model's bands: clamped
  EXPECT_EQ(loaded.trainer(config).model().sh_degree, 1);
}

// prune_min_contribution: at the end of densification the Gaussians below the threshold of blending weight
// over the training views go (here the two far outside the view, and any in-view one too faint); the rest
// stay, each at least at the threshold. 0 keeps every Gaussian.
TEST(TrainerSchedule, LowContributionGaussiansArePrunedAtTheEndOfDensification) {
  const ScheduleScene scene(/*outside=*/2);
  TrainConfig config = schedule_config();
  config.densify_until_fraction = 0.05;  // densification ends at iteration 5
  Trainer keep_all = scene.trainer(config);
  for (int i = 0; i < 5; ++i) keep_all.step();
  EXPECT_EQ(keep_all.model().size(), 10);

  config.prune_min_contribution = 0.05;
  Trainer trainer = scene.trainer(config);
  for (int i = 0; i < 4; ++i) trainer.step();
  EXPECT_EQ(trainer.model().size(), 10);
  trainer.step();
  const int64_t left = trainer.model().size();
  EXPECT_LE(left, 8);
  EXPECT_GE(left, 1);
  at::AutoGradMode no_grad(false);
  EXPECT_LT(trainer.model().means.select(1, 0).max().item<double>(), 50.0) << "the outside ones are gone";
  EXPECT_GE(blending_weights(trainer.model(), scene.camera).min().item<double>(), 0.05);
}

TEST(TrainConfig, JsonRoundTripAndUnknownKeys) {
  TrainConfig c;
  c.iterations = 1234;
  c.densify_grad_threshold = 0.0005;
  nlohmann::json j = c;
  EXPECT_EQ(j["iterations"], 1234);
  const auto back = j.get<TrainConfig>();
  EXPECT_EQ(back.iterations, 1234);
  EXPECT_DOUBLE_EQ(back.densify_grad_threshold, 0.0005);
  EXPECT_EQ(back.densify_until_iter(), 617);
  nlohmann::json bad = {{"iterationz", 5}};
  EXPECT_THROW(bad.get<TrainConfig>(), nlohmann::json::exception);
}

}  // namespace
}  // namespace gaps

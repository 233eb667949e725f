// The automatic Gaussian budget (budget.h): total variation, the budget it gives, and a run under it.
#include <cmath>
#include <fstream>

#include <ATen/ATen.h>
#include <gtest/gtest.h>
#include <nlohmann/json.hpp>

#include "gs_trainer/eval/image_stats.h"
#include "gs_trainer/train/budget.h"
#include "gs_trainer/train/trainer.h"
#include "tests/synthetic_run.h"
#include "tests/test_util.h"

namespace gaps {
namespace {

at::Tensor grey_image(const at::Tensor& level) { return level.unsqueeze(2).expand({-1, -1, 3}).contiguous(); }

TEST(TotalVariation, StepEdgeCountsOneUnitPerRow) {
  // 0 left of column 3, 1 from it: the central differences at columns 2 and 3 are 0.5 each.
  at::Tensor level = at::zeros({4, 6}, at::kFloat);
  level.narrow(1, 3, 3).fill_(1.0);
  EXPECT_NEAR(total_variation(grey_image(level)), 4.0, 1e-9);
}

TEST(TotalVariation, RampCountsInteriorMagnitudesAndOneSidedBorders) {
  const int h = 5, w = 7;
  const double a = 0.01, b = 0.02;  // I = a x + b y
  const at::Tensor x = at::arange(w, at::kDouble).view({1, w}), y = at::arange(h, at::kDouble).view({h, 1});
  const at::Tensor level = (a * x + b * y).to(at::kFloat);
  // Interior pixels see both slopes; border columns only the vertical one, border rows only the horizontal
  // one; the corners neither.
  const double expected = (h - 2) * (w - 2) * std::hypot(a, b) + 2 * (h - 2) * b + 2 * (w - 2) * a;
  EXPECT_NEAR(total_variation(grey_image(level)), expected, 1e-6);
}

TEST(TotalVariation, UsesTheLumaOfColour) {
  at::Tensor image = at::zeros({3, 4, 3}, at::kFloat);
  image.narrow(1, 2, 2).select(2, 1).fill_(1.0);  // a green edge: grey steps by 0.587
  EXPECT_NEAR(total_variation(image), 3 * 0.587, 1e-6);
}

TrainingView view_of(const at::Tensor& image) {
  TrainingView v;
  v.camera.width = static_cast<int>(image.size(1));
  v.camera.height = static_cast<int>(image.size(0));
  v.camera.fx = v.camera.fy = 10;
  v.camera.cx = v.camera.width / 2.0;
  v.camera.cy = v.camera.height / 2.0;
  v.image = image;
  return v;
}

std::vector<TrainingView> two_edge_views() {
  at::Tensor a = at::zeros({4, 6}, at::kFloat), b = at::zeros({10, 6}, at::kFloat);
  a.narrow(1, 3, 3).fill_(1.0);  // total variation 4
  b.narrow(1, 3, 3).fill_(0.5);  // 10 rows of 0.5
  return {view_of(grey_image(a)), view_of(grey_image(b))};
}

TEST(AutomaticBudget, IsTheDensityTimesTheViewsVariation) {
  EXPECT_EQ(automatic_budget(two_edge_views(), 100.0), 900);
  EXPECT_EQ(automatic_budget(two_edge_views(), 0.25), 2);  // 2.25 rounds to 2
  EXPECT_EQ(automatic_budget(two_edge_views(), 1e-6), 1);  // never below one Gaussian
  EXPECT_THROW(automatic_budget(two_edge_views(), 0.0), c10::Error);
}

GaussianModel one_gaussian() {
  GaussianModel m;
  m.max_sh_degree = 0;
  m.means = at::tensor({0.f, 0.f, 2.f}).view({1, 3});
  m.log_scales = at::full({1, 3}, -2.f);
  m.quats = at::tensor({1.f, 0.f, 0.f, 0.f}).view({1, 4});
  m.opacity_logits = at::zeros({1});
  m.sh_dc = at::zeros({1, 1, 3});
  m.sh_rest = at::zeros({1, 0, 3});
  return m;
}

TEST(AutomaticBudget, TheTrainerResolvesItIntoMaxGaussians) {
  TrainConfig config;
  config.device = "cpu";
  config.gaussians_per_variation = 100.0;
  Trainer trainer(one_gaussian(), two_edge_views(), config);
  EXPECT_EQ(trainer.config().max_gaussians, 900);
  config.max_gaussians = 50;  // a count given wins
  EXPECT_EQ(Trainer(one_gaussian(), two_edge_views(), config).config().max_gaussians, 50);
  config.max_gaussians = 0;
  config.gaussians_per_variation = 0;  // unlimited
  EXPECT_EQ(Trainer(one_gaussian(), two_edge_views(), config).config().max_gaussians, 0);
  config.gaussians_per_variation = TrainConfig{}.gaussians_per_variation;  // automatic: the default density
  ASSERT_LT(config.gaussians_per_variation, 0);
  EXPECT_EQ(Trainer(one_gaussian(), two_edge_views(), config).config().max_gaussians,
            automatic_budget(two_edge_views(), kDefaultGaussiansPerVariation));
}

struct BudgetRun : test::TempDirTest {};

// Densification every 10 iterations of a short synthetic run grows the model past its 2,000 initial points;
// under an automatic budget just above them it stops at the budget, and metrics.json records the budget.
TEST_F(BudgetRun, DensificationStopsAtTheAutomaticBudget) {
  test::write_small_scene(dir_);
  RunOptions o = test::short_run(dir_);
  o.config.densify_from_iter = 10;
  o.config.densification_interval = 10;
  o.config.densify_until_fraction = 1.0;
  o.config.densify_grad_threshold = 1e-7;
  o.config.gaussians_per_variation = 0.0;
  const auto quiet = [](const std::string&) {};
  const auto unlimited = run_pipeline(o, nullptr, quiet);
  ASSERT_TRUE(unlimited.ok()) << unlimited.status();
  ASSERT_EQ(unlimited->max_gaussians, 0);

  o.config.gaussians_per_variation = 1.0;
  const auto budgeted = run_pipeline(o, nullptr, quiet);
  ASSERT_TRUE(budgeted.ok()) << budgeted.status();
  ASSERT_GT(budgeted->max_gaussians, 0);
  o.config.gaussians_per_variation = 2000.5 / budgeted->max_gaussians;  // a budget of ~2,000 Gaussians
  const auto tight = run_pipeline(o, nullptr, quiet);
  ASSERT_TRUE(tight.ok()) << tight.status();
  EXPECT_NEAR(tight->max_gaussians, 2000, 20);  // the first budget was rounded
  ASSERT_GT(unlimited->num_gaussians, tight->max_gaussians + 100) << "the unlimited run must grow past it";
  EXPECT_LE(tight->num_gaussians, tight->max_gaussians);
  std::ifstream f(dir_ / "out" / "metrics.json");
  EXPECT_EQ(nlohmann::json::parse(f)["max_gaussians"].get<int64_t>(), tight->max_gaussians);
}

}  // namespace
}  // namespace gaps

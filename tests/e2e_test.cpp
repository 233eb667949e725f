// End to end on the CPU: the synthetic demo scene and the real LLFF fern scene (3 views, -r 8) go
// through loading, random initialisation, training, evaluation and output writing.
#include <filesystem>
#include <fstream>

#include <gtest/gtest.h>
#include <nlohmann/json.hpp>

#include "gs_trainer/model/gaussians.h"
#include "gs_trainer/pipeline.h"
#include "gs_trainer/scene/cameras_json.h"
#include "gs_trainer/synthetic.h"
#include "tests/synthetic_run.h"
#include "tests/test_util.h"

namespace gaps {
namespace {

using EndToEnd = test::TempDirTest;

struct Recorded {
  std::vector<TrainProgress> progress;
  RunResult result;
};

Recorded run(RunOptions o) {
  Recorded r;
  auto result = run_pipeline(
      o, [&](const TrainProgress& p) { r.progress.push_back(p); }, [](const std::string&) {});
  EXPECT_TRUE(result.ok()) << result.status();
  if (result.ok()) r.result = *result;
  return r;
}

void expect_outputs(const std::filesystem::path& out, int train_views, int test_views) {
  std::ifstream f(out / "metrics.json");
  ASSERT_TRUE(f.good());
  const auto j = nlohmann::json::parse(f);
  for (const char* key :
       {"psnr", "ssim", "lpips", "num_gaussians", "train_seconds", "iterations", "views", "device", "seed"})
    EXPECT_TRUE(j.contains(key)) << key;
  EXPECT_TRUE(j["lpips"].is_null()) << "no LPIPS backbone was given, so LPIPS must be null";
  EXPECT_EQ(j.value("init_method", ""), "random");  // both runs below start from random points
  EXPECT_EQ(j["per_view"].size(), static_cast<size_t>(test_views));
  auto model = load_gaussians_ply(out / "point_cloud.ply");
  ASSERT_TRUE(model.ok()) << model.status();
  EXPECT_EQ(model->size(), j["num_gaussians"].get<int64_t>());
  int renders = 0;
  for (const auto& e : std::filesystem::directory_iterator(out / "renders")) renders += e.path().extension() == ".png";
  EXPECT_EQ(renders, test_views);
  // cameras.json: the training views, then the test views in per_view's order.
  const auto cameras = read_cameras_json(out / "cameras.json");
  ASSERT_TRUE(cameras.ok()) << cameras.status();
  ASSERT_EQ(cameras->size(), static_cast<size_t>(train_views + test_views));
  for (int i = 0; i < train_views + test_views; ++i)
    EXPECT_EQ((*cameras)[i].split, i < train_views ? "train" : "test") << i;
  for (int i = 0; i < test_views; ++i)
    EXPECT_EQ((*cameras)[train_views + i].camera.name, j["per_view"][i]["image"].get<std::string>()) << i;
}

TEST_F(EndToEnd, SyntheticSceneFromThreeViews) {
  const auto dir = dir_;
  ASSERT_TRUE(write_synthetic_scene(dir / "scene", {}).ok());
  RunOptions o = test::short_run(dir);
  o.random_points = 4000;
  o.config.iterations = 600;
  const auto r = run(o);
  ASSERT_FALSE(r.progress.empty());
  EXPECT_LT(r.progress.back().loss, 0.6 * r.progress.front().loss);
  EXPECT_GT(r.result.metrics.psnr, 14.0);
  expect_outputs(o.out_dir, 3, 2);
}

TEST_F(EndToEnd, FernThreeViewsLossFallsAndPsnrClearsAFloor) {
  const std::filesystem::path fern = std::filesystem::path(GAPS_DATA_DIR) / "llff" / "fern";
  if (!std::filesystem::exists(fern)) GTEST_SKIP() << "benchmark data not found at " << fern;
  const RunOptions o = test::fern_short_run(dir_ / "out");
  const auto r = run(o);
  ASSERT_GE(r.progress.size(), 2u);
  for (const auto& p : r.progress) EXPECT_TRUE(std::isfinite(p.loss)) << "iteration " << p.iteration;
  EXPECT_LT(r.progress.back().loss, 0.8 * r.progress.front().loss);
  EXPECT_GT(r.result.metrics.psnr, 14.0);
  EXPECT_GT(r.result.metrics.ssim, 0.3);
  expect_outputs(o.out_dir, 3, 3);
}

}  // namespace
}  // namespace gaps

#pragma once
// LPIPS with the real VGG16 weights that scripts/setup.sh converts, on fern: a short run on `device` must
// report a numeric LPIPS for the run and every test view, and our LPIPS of its renders and of fern's photos
// must match PyPI's `lpips` on torchvision's vgg16 loaded with the same weights
// (tests/scripts/lpips_real_reference.py). Shared by lpips_test.cpp (CPU) and gpu/lpips_cuda_test.cpp.
#include <filesystem>
#include <fstream>
#include <string>
#include <utility>
#include <vector>

#include <ATen/ATen.h>
#include <ATen/core/grad_mode.h>
#include <gtest/gtest.h>
#include <nlohmann/json.hpp>

#include "common/image_io.h"
#include "gs_trainer/eval/lpips.h"
#include "gs_trainer/pipeline.h"
#include "tests/lpips_test_util.h"
#include "tests/synthetic_run.h"

namespace gaps::test {

constexpr double kRealParityTolerance = 1e-4;  // per image, absolute

inline void check_fern_run_lpips(const std::filesystem::path& dir, const std::string& device) {
  namespace fs = std::filesystem;
  const fs::path weights = default_lpips_weights_path();
  std::error_code ec;
  // Never a skip: the test suite's own set-up (scripts/setup.sh) makes this file.
  ASSERT_TRUE(fs::is_regular_file(weights, ec))
      << "LPIPS weights missing at " << weights << ": bash scripts/setup.sh makes them";
  const fs::path fern = fs::path(GAPS_DATA_DIR) / "llff" / "fern";
  if (!fs::exists(fern / "images_8", ec)) GTEST_SKIP() << "benchmark data not found at " << fern / "images_8";

  RunOptions o = fern_short_run(dir / "out");
  o.config.device = device;
  o.eval_every = 0;
  o.lpips_weights = weights;
  absl::StatusOr<RunResult> result = run_pipeline(
      o, [](const TrainProgress&) {}, [](const std::string&) {});
  ASSERT_TRUE(result.ok()) << result.status();
  ASSERT_TRUE(result->metrics.lpips.has_value());
  EXPECT_GT(*result->metrics.lpips, 0.0);
  EXPECT_LT(*result->metrics.lpips, 1.0);

  std::ifstream metrics_file(o.out_dir / "metrics.json");
  const nlohmann::json metrics = nlohmann::json::parse(metrics_file);
  ASSERT_TRUE(metrics["lpips"].is_number()) << metrics["lpips"];
  ASSERT_EQ(metrics["per_view"].size(), 3u);
  std::vector<std::pair<std::string, std::string>> pairs;
  for (const nlohmann::json& view : metrics["per_view"]) {
    ASSERT_TRUE(view["lpips"].is_number()) << view;
    const std::string name = view["image"].get<std::string>();
    pairs.emplace_back((o.out_dir / "renders" / (fs::path(name).stem().string() + ".png")).string(),
                       (fern / "images_8" / name).string());
  }
  // Two photographs of the scene, and a photograph with itself (distance 0).
  pairs.emplace_back(pairs[0].second, pairs[1].second);
  pairs.emplace_back(pairs[2].second, pairs[2].second);

  nlohmann::json pairs_json = nlohmann::json::array();
  for (const auto& [a, b] : pairs) pairs_json.push_back({a, b});
  const fs::path pairs_file = dir / "pairs.json", distances_file = dir / "distances.json";
  std::ofstream(pairs_file) << pairs_json.dump();
  const std::string command = std::string(GAPS_PYTHON) + " " + GAPS_TEST_SCRIPTS_DIR +
                              "/scripts/lpips_real_reference.py --weights " + weights.string() + " --pairs " +
                              pairs_file.string() + " --out " + distances_file.string();
  const auto [rc, output] = run_command(command);
  if (rc == kMissingPythonModule) GTEST_SKIP() << "the reference needs Python modules: " << output;
  ASSERT_EQ(rc, 0) << command << "\n" << output;
  std::ifstream distances_in(distances_file);
  const std::vector<double> expected = nlohmann::json::parse(distances_in).get<std::vector<double>>();
  ASSERT_EQ(expected.size(), pairs.size());

  absl::StatusOr<Lpips> lpips = Lpips::load_safetensors(weights.string());
  ASSERT_TRUE(lpips.ok()) << lpips.status();
  const at::Device on(device);
  lpips->to(on);
  at::NoGradGuard no_grad;
  // cuDNN may convolve in TF32 by default, which moves distances by ~1e-4 relative: off for the comparison.
  at::Context& context = at::globalContext();
  const bool tf32 = context.allowTF32CuDNN();
  context.setAllowTF32CuDNN(false);
  for (size_t i = 0; i < pairs.size(); ++i) {
    absl::StatusOr<at::Tensor> a = read_image(pairs[i].first), b = read_image(pairs[i].second);
    ASSERT_TRUE(a.ok() && b.ok()) << pairs[i].first << " / " << pairs[i].second;
    const double d = lpips->distance(a->to(on), b->to(on)).item<double>();
    EXPECT_NEAR(d, expected[i], kRealParityTolerance) << pairs[i].first << " vs " << pairs[i].second;
    // The run scored its float renders; the PNGs differ from them by rounding alone.
    if (i < 3) EXPECT_NEAR(d, metrics["per_view"][i]["lpips"].get<double>(), 5e-3) << pairs[i].first;
  }
  context.setAllowTF32CuDNN(tf32);
  EXPECT_GT(expected[3], 0.05) << "two different photographs";
  EXPECT_EQ(expected[4], 0.0);
}

}  // namespace gaps::test

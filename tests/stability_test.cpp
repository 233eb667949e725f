// Stability where methods fail: near-degenerate inputs (two views, two nearly identical views, a wide-baseline
// pair) and a
// generator returning garbage. Each run must finish with finite metrics or stop with a named error, and the
// garbage must not cost accuracy against vanilla.
#include <cmath>
#include <fstream>
#include <optional>

#include <ATen/ATen.h>
#include <gtest/gtest.h>
#include <nlohmann/json.hpp>

#include "diffusion_worker/backend_registry.h"
#include "gs_trainer/pipeline.h"
#include "gs_trainer/synthetic.h"
#include "tests/synthetic_run.h"
#include "tests/test_util.h"

namespace gaps {
namespace {

using test::read_json;

void quiet(const std::string&) {}

// Uniform noise of the requested size: what a broken backend (wrong checkpoint, NaN-free garbage) returns.
class NoiseGenerator : public Generator {
 public:
  std::string name() const override { return "noise (test)"; }
  absl::Status adapt(const std::vector<ReferenceView>&, const std::optional<SceneAdaptation>&) override {
    return absl::OkStatus();
  }
  absl::StatusOr<std::vector<at::Tensor>> generate(const std::vector<GenerationRequest>& requests) override {
    std::vector<at::Tensor> out;
    for (const auto& r : requests) out.push_back(at::rand_like(r.render_rgb));
    return out;
  }
};

struct Stability : test::TempDirTest {
  // A short method schedule: phases every 30 iterations after a 30-iteration warmup.
  RunOptions synthetic_options(Variant variant, Generator* generator) {
    RunOptions o = test::short_run(dir_, variant, generator);
    o.views = 2;
    o.html_report = false;
    return o;
  }
  void write_scene() { test::write_small_scene(dir_); }
  std::unique_ptr<Generator> reproject() {
    auto g = make_generator("reproject", "");
    EXPECT_TRUE(g.ok()) << g.status();
    return g.ok() ? std::move(*g) : nullptr;
  }
};

// Fern at -r 8 from 4,000 random points, 120 iterations; nullopt (and a skip) without the data.
std::optional<RunOptions> short_fern_run(int views) {
  const std::filesystem::path fern = std::filesystem::path(GAPS_DATA_DIR) / "llff" / "fern";
  if (!std::filesystem::exists(fern)) return std::nullopt;
  RunOptions o;
  o.scene_dir = fern;
  o.views = views;
  o.resolution = 8;
  o.init = "random";
  o.random_points = 4000;
  o.config.iterations = 120;
  o.html_report = false;
  o.save_renders = false;
  return o;
}

// Switches a short_fern_run to the method: phases at iterations 40 and 80, 4 pseudo-views each.
void use_method(RunOptions& o, Generator* generator) {
  o.variant = Variant::kFull;
  o.generator = generator;
  o.gaps.warmup_iterations = 40;
  o.gaps.phase_interval = 40;
  o.gaps.n_active = 4;
}

struct PhaseCounts {
  int generated = 0, admitted = 0;
};

PhaseCounts count_pseudo_views(const std::filesystem::path& out_dir) {
  PhaseCounts c;
  for (const auto& phase : read_json(out_dir / "phases.json")) {
    c.generated += static_cast<int>(phase["selection"].size());
    c.admitted += phase["admitted"].get<int>();
  }
  return c;
}

void expect_finished_and_finite(const absl::StatusOr<RunResult>& r, const std::filesystem::path& out) {
  ASSERT_TRUE(r.ok()) << r.status();
  EXPECT_TRUE(std::isfinite(r->metrics.psnr));
  EXPECT_TRUE(std::isfinite(r->metrics.ssim));
  EXPECT_GT(r->num_gaussians, 0);
  EXPECT_EQ(read_json(out / "metrics.json")["status"], "ok");
}

TEST_F(Stability, TwoViewsWithTheMethod) {
  write_scene();
  auto generator = reproject();
  ASSERT_TRUE(generator);
  const RunOptions o = synthetic_options(Variant::kFull, generator.get());
  const auto r = run_pipeline(o, nullptr, quiet);
  expect_finished_and_finite(r, o.out_dir);
  const auto phases = read_json(o.out_dir / "phases.json");
  EXPECT_EQ(phases.size(), 2u);  // at iterations 30 and 60
}

// The two training views (frames 1 and 15 of 16 with views = 2) made nearly identical: frame 15 becomes
// frame 1's image at frame 1's pose moved by a millimetre. Pair interpolation and extrapolation then span
// almost nothing.
TEST_F(Stability, TwoNearlyIdenticalViewsWithTheMethod) {
  write_scene();
  const auto transforms_path = dir_ / "scene" / "transforms.json";
  nlohmann::json transforms = read_json(transforms_path);
  auto& frames = transforms["frames"];
  frames[15]["file_path"] = frames[1]["file_path"];
  frames[15]["transform_matrix"] = frames[1]["transform_matrix"];
  frames[15]["transform_matrix"][0][3] = frames[1]["transform_matrix"][0][3].get<double>() + 1e-3;
  std::ofstream(transforms_path) << transforms.dump(2);
  auto generator = reproject();
  ASSERT_TRUE(generator);
  const RunOptions o = synthetic_options(Variant::kFull, generator.get());
  const auto r = run_pipeline(o, nullptr, quiet);
  expect_finished_and_finite(r, o.out_dir);
}

// Fern, 3 views, a short schedule with two phases of noise. Vanilla and the method start from the same
// random points and seed; the method may not lose more than a small margin to vanilla. The paper's two
// admission criteria admit uniform noise (its mean residual against a render is about 1/3 < tau_res); the
// default gate's structure criterion (admit_min_structure 0.4 on the generator's proposal) rejects it.
TEST_F(Stability, GarbageGeneratorOnFernCostsNoAccuracy) {
  std::optional<RunOptions> o = short_fern_run(3);
  if (!o) GTEST_SKIP() << "benchmark data not found under " << GAPS_DATA_DIR;
  o->out_dir = dir_ / "vanilla";
  const auto vanilla = run_pipeline(*o, nullptr, quiet);
  ASSERT_TRUE(vanilla.ok()) << vanilla.status();

  NoiseGenerator noise;
  o->out_dir = dir_ / "noise";
  use_method(*o, &noise);
  const auto method = run_pipeline(*o, nullptr, quiet);
  ASSERT_TRUE(method.ok()) << method.status();
  const PhaseCounts views = count_pseudo_views(o->out_dir);
  EXPECT_EQ(views.generated, 8);  // 2 phases x 4 views
  RecordProperty("noise_views_admitted", views.admitted);
  RecordProperty("psnr_vanilla", std::to_string(vanilla->metrics.psnr));
  RecordProperty("psnr_noise", std::to_string(method->metrics.psnr));
  std::cout << "noise views admitted " << views.admitted << " of " << views.generated << "; PSNR vanilla "
            << vanilla->metrics.psnr << ", with noise " << method->metrics.psnr << "\n";
  EXPECT_EQ(views.admitted, 0) << "the admission gate let uniform noise through";
  EXPECT_GE(method->metrics.psnr, vanilla->metrics.psnr - 0.3);
}

// A wide-baseline pair: fern with 2 training views, which the split takes as the first and the last of the
// non-test frames (the widest pair the scene has). Every pair interpolation then spans the whole scene and
// the extrapolated poses look past what either view saw. The method with the reproject backend, from the
// same start and seed as vanilla, must finish finite, generate at every phase, and not fall below vanilla
// by more than the seed noise of so short a run.
TEST_F(Stability, WideBaselinePairOnFern) {
  std::optional<RunOptions> o = short_fern_run(2);
  if (!o) GTEST_SKIP() << "benchmark data not found under " << GAPS_DATA_DIR;
  o->out_dir = dir_ / "vanilla";
  const auto vanilla = run_pipeline(*o, nullptr, quiet);
  expect_finished_and_finite(vanilla, o->out_dir);

  auto generator = reproject();
  ASSERT_TRUE(generator);
  o->out_dir = dir_ / "full";
  use_method(*o, generator.get());
  const auto method = run_pipeline(*o, nullptr, quiet);
  expect_finished_and_finite(method, o->out_dir);
  const PhaseCounts views = count_pseudo_views(o->out_dir);
  std::cout << "wide pair: " << views.admitted << " of " << views.generated << " pseudo-views admitted; PSNR vanilla "
            << vanilla->metrics.psnr << ", method " << method->metrics.psnr << "\n";
  RecordProperty("psnr_vanilla", std::to_string(vanilla->metrics.psnr));
  RecordProperty("psnr_method", std::to_string(method->metrics.psnr));
  EXPECT_EQ(views.generated, 8);  // 2 phases x 4 views
  EXPECT_GE(method->metrics.psnr, vanilla->metrics.psnr - 0.3);
}

}  // namespace
}  // namespace gaps

// What a run reports about itself: the divergence guard (non-finite loss or parameters stop the run with
// the iteration and the culprit named), the evaluation curve, peak memory and generator time in
// metrics.json, and the self-contained HTML report. Peak memory on CUDA: gpu/run_monitoring_cuda_test.cpp.
#include <cmath>
#include <fstream>
#include <limits>
#include <regex>
#include <sstream>

#include <ATen/ATen.h>
#include <gtest/gtest.h>
#include <nlohmann/json.hpp>

#include "absl/strings/str_format.h"
#include "gs_trainer/pipeline.h"
#include "gs_trainer/report.h"
#include "gs_trainer/synthetic.h"
#include "gs_trainer/train/divergence.h"
#include "tests/run_monitoring_test_util.h"
#include "tests/synthetic_run.h"
#include "tests/test_util.h"

namespace gaps {
namespace {

using test::read_text;

using test::read_json;
using test::RunMonitoring;

GaussianModel small_model() {
  PointCloud points;
  points.xyz = at::rand({50, 3}, at::kFloat);
  points.rgb = at::rand({50, 3}, at::kFloat);
  return gaussians_from_points(points, 1);
}

TEST(DivergenceGuard, FiniteLossAndParametersPass) {
  DivergenceGuard guard(10, 100);
  const GaussianModel model = small_model();
  for (int it = 1; it <= 100; ++it) EXPECT_TRUE(guard.observe(it, at::scalar_tensor(0.5), model).ok()) << it;
}

TEST(DivergenceGuard, NamesTheFirstNonFiniteLossAtTheNextCheck) {
  DivergenceGuard guard(10, 100);
  const GaussianModel model = small_model();
  for (int it = 1; it <= 9; ++it) {
    const double loss = it == 7 ? std::numeric_limits<double>::infinity() : 0.5;
    EXPECT_TRUE(guard.observe(it, at::scalar_tensor(loss), model).ok()) << "checked before the check point " << it;
  }
  const absl::Status st = guard.observe(10, at::scalar_tensor(0.5), model);
  ASSERT_FALSE(st.ok());
  EXPECT_TRUE(is_divergence(st));
  EXPECT_NE(st.message().find("iteration 10"), std::string::npos) << st;
  EXPECT_NE(st.message().find("loss (first at iteration 7)"), std::string::npos) << st;
  EXPECT_EQ(st.message().find("parameters"), std::string::npos) << st;
}

TEST(DivergenceGuard, NamesPoisonedParametersAndCounts) {
  DivergenceGuard guard(10, 25);
  GaussianModel model = small_model();
  model.log_scales[3][1] = std::numeric_limits<float>::quiet_NaN();
  model.log_scales[4][0] = std::numeric_limits<float>::infinity();
  for (int it = 21; it <= 24; ++it) EXPECT_TRUE(guard.observe(it, at::scalar_tensor(0.5), model).ok());
  const absl::Status st = guard.observe(25, at::scalar_tensor(0.5), model);  // the last iteration is checked
  ASSERT_TRUE(is_divergence(st)) << st;
  EXPECT_NE(st.message().find("iteration 25"), std::string::npos) << st;
  EXPECT_NE(st.message().find("log_scales 2 of 150 values"), std::string::npos) << st;
  EXPECT_EQ(st.message().find("means"), std::string::npos) << st;
  EXPECT_EQ(st.message().find("loss"), std::string::npos) << st;
}

TEST(DivergenceGuard, OtherErrorsAreNotDivergence) {
  EXPECT_FALSE(is_divergence(absl::InternalError("training diverged at iteration 3")));
  EXPECT_FALSE(is_divergence(absl::AbortedError("cancelled")));
}

int count(const std::string& text, const std::string& what) {
  int n = 0;
  for (size_t at = text.find(what); at != std::string::npos; at = text.find(what, at + 1)) ++n;
  return n;
}

// Echoes the render for even request indices (admissible) and returns noise for odd ones (garbage).
class HalfGarbageGenerator : public Generator {
 public:
  std::string name() const override { return "half-garbage (test)"; }
  absl::Status adapt(const std::vector<ReferenceView>&, const std::optional<SceneAdaptation>&) override {
    return absl::OkStatus();
  }
  absl::StatusOr<std::vector<at::Tensor>> generate(const std::vector<GenerationRequest>& requests) override {
    std::vector<at::Tensor> out;
    for (size_t i = 0; i < requests.size(); ++i)
      out.push_back(i % 2 == 0 ? requests[i].render_rgb.clone() : at::rand_like(requests[i].render_rgb));
    return out;
  }
};

TEST_F(RunMonitoring, CurvePeakMemoryAndReportOfAVanillaRun) {
  const RunOptions o = options();
  auto r = run_pipeline(o, nullptr, [](const std::string&) {});
  ASSERT_TRUE(r.ok()) << r.status();
  const auto m = read_json(o.out_dir / "metrics.json");
  EXPECT_EQ(m["status"], "ok");
  EXPECT_EQ(m["eval_every"], 20);
  ASSERT_EQ(m["curve"].size(), 3u);
  double previous_seconds = 0;
  for (size_t k = 0; k < 3; ++k) {
    const auto& p = m["curve"][k];
    EXPECT_EQ(p["iteration"], 20 * static_cast<int>(k + 1));
    EXPECT_GT(p["train_seconds"].get<double>(), previous_seconds);
    previous_seconds = p["train_seconds"].get<double>();
    EXPECT_TRUE(std::isfinite(p["psnr"].get<double>()));
    EXPECT_TRUE(p["lpips"].is_null());
    EXPECT_GT(p["num_gaussians"].get<int64_t>(), 0);
  }
  // The last point is the final evaluation, and its time is the run's training time.
  EXPECT_DOUBLE_EQ(m["curve"][2]["psnr"].get<double>(), m["psnr"].get<double>());
  EXPECT_DOUBLE_EQ(m["curve"][2]["train_seconds"].get<double>(), m["train_seconds"].get<double>());
  EXPECT_EQ(m["curve"][2]["num_gaussians"], m["num_gaussians"]);
  EXPECT_EQ(m["peak_memory"]["kind"], "cpu_rss");
  EXPECT_GT(m["peak_memory"]["bytes"].get<int64_t>(), 1 << 20);
  EXPECT_TRUE(m["generator_seconds"].is_null());

  const std::string html = read_text(o.out_dir / "report.html");
  ASSERT_FALSE(html.empty());
  EXPECT_EQ(count(html, "http"), 0) << "the report must not reach the network";
  // The report's own page runs no script; the viewer's does, inside its iframe (an escaped srcdoc page).
  EXPECT_EQ(count(html, "<script"), 0);
  EXPECT_EQ(count(html, "<iframe class=\"viewer\""), 1);
  EXPECT_GT(count(html, "&lt;script"), 0);
  EXPECT_EQ(count(html, "<svg"), 2);  // PSNR over time, Gaussians over iterations
  // Two test views of the synthetic scene, each as ground truth and render.
  EXPECT_EQ(count(html, "src=\"data:image/png;base64,"), 4);
  EXPECT_NE(html.find("No pseudo-view phases"), std::string::npos);
  const std::string init_row = absl::StrFormat("<tr><th>initial points</th><td>%s, %d points in %.1f s</td></tr>",
                                               m["init_method"].get<std::string>(), m["init_points"].get<int64_t>(),
                                               m["init_seconds"].get<double>());
  EXPECT_NE(html.find(init_row), std::string::npos) << init_row;
}

TEST_F(RunMonitoring, ReportShowsAdmittedAndRejectedPseudoViewsAndGeneratorTime) {
  HalfGarbageGenerator generator;
  RunOptions o = options();
  o.config.iterations = 90;
  o.eval_every = 0;
  o.variant = Variant::kFull;
  o.generator = &generator;  // phases at 30 and 60 (test::short_run)
  // The paper's residual threshold (0.7) admits uniform noise (mean residual about 1/3 against a render);
  // a stricter one makes the decisions of this generator known: echoes in, noise out.
  o.gaps.admit_max_residual = 0.2;
  auto r = run_pipeline(o, nullptr, [](const std::string&) {});
  ASSERT_TRUE(r.ok()) << r.status();
  const auto m = read_json(o.out_dir / "metrics.json");
  ASSERT_TRUE(m["generator_seconds"].is_number());
  EXPECT_GT(m["generator_seconds"].get<double>(), 0.0);
  EXPECT_LT(m["generator_seconds"].get<double>(), m["train_seconds"].get<double>());
  EXPECT_TRUE(m["curve"].empty());

  const auto phases = read_json(o.out_dir / "phases.json");
  int admitted = 0, rejected = 0, garbage_admitted = 0;
  for (const auto& phase : phases)
    for (size_t k = 0; k < phase["selection"].size(); ++k) {
      const bool a = phase["selection"][k]["admitted"];
      (a ? admitted : rejected) += 1;
      garbage_admitted += a && k % 2 == 1;
    }
  EXPECT_GT(admitted, 0);
  EXPECT_GT(rejected, 0);
  EXPECT_EQ(garbage_admitted, 0) << "the admission gate let noise through";

  const std::string html = read_text(o.out_dir / "report.html");
  EXPECT_EQ(count(html, "http"), 0);
  EXPECT_EQ(count(html, "<figure class=\"admitted\"><img"), admitted);
  EXPECT_EQ(count(html, "<figure class=\"rejected\"><img"), rejected);
  EXPECT_EQ(count(html, "<h3>Phase "), static_cast<int>(phases.size()));
  // The selection diagnostic: per phase every scored candidate, the picked ones marked with their decision.
  EXPECT_EQ(count(html, "<details><summary>Selection: "), static_cast<int>(phases.size()));
  EXPECT_EQ(count(html, "<b>picked</b>, admitted"), admitted);
  EXPECT_EQ(count(html, "<b>picked</b>, rejected"), rejected);
  EXPECT_EQ(count(html, "DEGRADED"), 0);
  EXPECT_EQ(count(html, "<tr><th>diffusion phases</th><td>2 run, 0 skipped</td></tr>"), 1);
}

TEST_F(RunMonitoring, AbsurdLearningRateStopsTheRunAsDiverged) {
  RunOptions o = options();
  o.config.scaling_lr = 1e30;  // exp(log_scale) overflows within a few steps
  o.config.feature_lr = 1e30;
  auto r = run_pipeline(o, nullptr, [](const std::string&) {});
  ASSERT_FALSE(r.ok());
  EXPECT_TRUE(is_divergence(r.status())) << r.status();
  const auto m = read_json(o.out_dir / "metrics.json");
  EXPECT_EQ(m["status"], "diverged");
  EXPECT_TRUE(m["psnr"].is_null());
  const std::string error = m["error"];
  EXPECT_TRUE(std::regex_search(error, std::regex("at iteration [0-9]+ .*non-finite"))) << error;
  EXPECT_TRUE(error.find("loss") != std::string::npos || error.find("parameters") != std::string::npos) << error;
}

TEST(SvgLineChart, ScalesPointsIntoThePlotAndSkipsNonFinite) {
  const std::string svg = svg_line_chart("t", "x", "y", {{"a", {{0, 10}, {5, 20}, {10, NAN}}}});
  EXPECT_EQ(count(svg, "<circle"), 2);
  std::smatch match;
  ASSERT_TRUE(std::regex_search(svg, match, std::regex("points=\"([^\"]*)\"")));
  std::istringstream points(match[1].str());
  double x, y;
  char comma;
  while (points >> x >> comma >> y) {
    EXPECT_GE(x, 70);
    EXPECT_LE(x, 540);
    EXPECT_GE(y, 30);
    EXPECT_LE(y, 290);
  }
  EXPECT_NE(svg_line_chart("t", "x", "y", {}).find("no data"), std::string::npos);
}

}  // namespace
}  // namespace gaps

// The alternating schedule: phases at the right iterations, selection, generation, admission, pseudo steps
// and DropGaussian, driven by a test generator whose output is known.
#include <ATen/ATen.h>
#include <gtest/gtest.h>

#include <map>
#include <set>
#include <string>
#include <vector>

#include "absl/strings/match.h"
#include "common/npy.h"
#include "diffusion_worker/backend_registry.h"
#include "gs_trainer/gaps/training.h"
#include "gs_trainer/pipeline.h"
#include "gs_trainer/scene/cameras_json.h"
#include "gs_trainer/scene/run_files.h"
#include "gs_trainer/synthetic.h"
#include "tests/synthetic_run.h"
#include "tests/test_util.h"

namespace gaps {
namespace {

using test::read_json;

// Returns the render it was given, blended towards mid-grey by `noise`: admission depends on `noise`.
class EchoGenerator : public Generator {
 public:
  explicit EchoGenerator(double noise) : noise_(noise) {}
  std::string name() const override { return "echo (test)"; }
  absl::Status adapt(const std::vector<ReferenceView>& views,
                     const std::optional<SceneAdaptation>& adaptation) override {
    adapted_views = static_cast<int>(views.size());
    adaptations += 1;
    generations_before_adapting = calls;
    this->adaptation = adaptation;
    last_notes = adapt_notes;
    return absl::OkStatus();
  }
  absl::StatusOr<std::vector<at::Tensor>> generate(const std::vector<GenerationRequest>& requests) override {
    std::vector<at::Tensor> out;
    for (const auto& r : requests) {
      EXPECT_FALSE(r.references.empty());
      EXPECT_GE(r.strength, 0.3 - 1e-12);
      EXPECT_LE(r.strength, 0.85 + 1e-12);
      out.push_back(r.render_rgb * (1 - noise_) + 0.5 * noise_);
      EXPECT_TRUE(r.inpaint.has_value());
      if (r.inpaint) inpaint = *r.inpaint;
      ip_adapter_scale = r.ip_adapter_scale;
    }
    calls += 1;
    last_notes = generate_notes;
    return out;
  }
  std::vector<std::string> notes() const override { return last_notes; }
  std::map<std::string, double> stage_seconds() const override { return {{"echo", 0.25 * calls}}; }
  int calls = 0;
  int adapted_views = 0;
  int adaptations = 0, generations_before_adapting = -1;
  std::optional<SceneAdaptation> adaptation;
  InpaintSettings inpaint;                               // of the last request
  std::optional<double> ip_adapter_scale;                // of the last request
  std::vector<std::string> adapt_notes, generate_notes;  // what adapt() and generate() report
  std::vector<std::string> last_notes;

 private:
  double noise_;
};

// Each channel of the render pushed to the far end of [0, 1]: every pixel's residual is at least 0.5, so the
// uncertainty variance (mean u²) is at least 0.25 and a residual threshold below 0.5 rejects every view.
class ContraryGenerator : public Generator {
 public:
  std::string name() const override { return "contrary (test)"; }
  absl::Status adapt(const std::vector<ReferenceView>&, const std::optional<SceneAdaptation>&) override {
    return absl::OkStatus();
  }
  absl::StatusOr<std::vector<at::Tensor>> generate(const std::vector<GenerationRequest>& requests) override {
    std::vector<at::Tensor> out;
    for (const auto& r : requests) out.push_back((r.render_rgb < 0.5).to(r.render_rgb.scalar_type()));
    return out;
  }
};

struct GapsTrainingTest : test::TempDirTest {
  RunOptions options(Variant variant, Generator* generator) { return test::short_run(dir_, variant, generator); }
  void SetUp() override {
    test::TempDirTest::SetUp();
    test::write_small_scene(dir_);
  }
};

TEST_F(GapsTrainingTest, FullVariantRunsPhasesAdmitsAndStaysFinite) {
  EchoGenerator gen(0.05);
  RunOptions run = options(Variant::kFull, &gen);
  run.gaps.inpaint_depth_threshold = 0.3;  // GapsConfig's two-stage settings reach the generator
  run.gaps.inpaint_uncovered_fraction = 0.05;
  run.gaps.inpaint_dilation = 9;
  run.gaps.lora_rank = 3;  // and its generation controls
  run.gaps.lora_steps = 20;
  run.gaps.ip_adapter_scale = 0.25;
  auto r = run_pipeline(run, nullptr, [](const std::string&) {});
  ASSERT_TRUE(r.ok()) << r.status();
  EXPECT_TRUE(std::isfinite(r->metrics.psnr));
  EXPECT_EQ(gen.calls, 2);  // phases at iterations 30 and 60
  EXPECT_EQ(gen.adapted_views, 3);
  EXPECT_EQ(gen.inpaint.depth_threshold, 0.3);
  EXPECT_EQ(gen.inpaint.uncovered_fraction, 0.05);
  EXPECT_EQ(gen.inpaint.dilation, 9);
  ASSERT_TRUE(gen.adaptation.has_value());
  EXPECT_EQ(gen.adaptation->lora_rank, 3);
  EXPECT_EQ(gen.adaptation->lora_steps, 20);
  EXPECT_EQ(gen.ip_adapter_scale, std::optional<double>(0.25));
  const auto phases = read_json(dir_ / "out" / "phases.json");
  ASSERT_EQ(phases.size(), 2u);
  for (const auto& p : phases) {
    EXPECT_EQ(p["selection"].size(), 4u);
    EXPECT_GT(p["candidates"].size(), 4u);
    EXPECT_GT(p["admitted"].get<int>(), 0);
    EXPECT_FALSE(p.contains("generator_notes")) << "a generator that honours everything";
  }
  EXPECT_TRUE(std::filesystem::exists(dir_ / "out" / "pseudo_views" / "phase_00"));
  EXPECT_EQ(read_json(dir_ / "out" / "metrics.json")["variant"], "full");
}

// The active set after every phase: this phase's admitted views, and older ones only while they are younger
// than active_max_age and within active_size; what left is listed with why, the pool with what is new in it.
TEST_F(GapsTrainingTest, TheActiveSetIsRefreshedEveryPhase) {
  EchoGenerator gen(0.05);
  RunOptions run = options(Variant::kFull, &gen);
  run.config.iterations = 120;  // phases at 30, 60 and 90
  run.gaps.active_max_age = 1;  // a view trains for one phase interval only
  auto r = run_pipeline(run, nullptr, [](const std::string&) {});
  ASSERT_TRUE(r.ok()) << r.status();
  const auto phases = read_json(dir_ / "out" / "phases.json");
  ASSERT_EQ(phases.size(), 3u);
  std::set<int> before;
  for (const auto& p : phases) {
    std::set<int> admitted, active, entered, retired;
    for (const auto& s : p["selection"])
      if (s["admitted"].get<bool>()) admitted.insert(s["id"].get<int>());
    for (const auto& id : p["active"]) active.insert(id.get<int>());
    for (const auto& id : p["entered"]) entered.insert(id.get<int>());
    for (const auto& v : p["retired"]) {
      retired.insert(v["id"].get<int>());
      EXPECT_FALSE(v["reason"].get<std::string>().empty());
    }
    EXPECT_FALSE(admitted.empty());
    EXPECT_EQ(entered, admitted);
    EXPECT_EQ(active, admitted) << "older views age out after one phase";
    for (int id : before) EXPECT_TRUE(retired.count(id)) << "view " << id << " of the last phase left";
    EXPECT_EQ(p["pool"]["size"].get<size_t>(), p["candidates"].size());
    EXPECT_LE(p["pool"]["never_generated"].get<int>(), p["pool"]["size"].get<int>());
    before = active;
  }
  EXPECT_EQ(phases[0]["pool"]["never_generated"].get<size_t>(), phases[0]["candidates"].size());
  EXPECT_LT(phases[1]["pool"]["never_generated"].get<size_t>(), phases[1]["candidates"].size());

  // Without the refresh every admitted view stays.
  RunOptions grow = options(Variant::kFull, &gen);
  grow.config.iterations = 120;
  grow.gaps.refresh_active_set = false;
  grow.out_dir = dir_ / "grow";
  ASSERT_TRUE(run_pipeline(grow, nullptr, [](const std::string&) {}).ok());
  const auto grown = read_json(dir_ / "grow" / "phases.json");
  std::set<int> ever;
  for (const auto& p : grown) {
    for (const auto& s : p["selection"])
      if (s["admitted"].get<bool>()) ever.insert(s["id"].get<int>());
    EXPECT_EQ(p["active"].size(), ever.size());
  }
}

// Asynchronous phases: training goes on while a phase's views are generated from the model as the phase found it;
// they are judged exactly async_iterations later, or before the next phase, whatever the timing; a phase
// started near the end is judged at the end.
TEST_F(GapsTrainingTest, AsynchronousPhasesAdmitTheirViewsAFixedNumberOfIterationsLater) {
  EchoGenerator gen(0.05);
  RunOptions run = options(Variant::kFull, &gen);
  run.config.iterations = 120;  // phases before iterations 30, 60 and 90
  run.gaps.async_iterations = 10;
  auto first = run_pipeline(run, nullptr, [](const std::string&) {});
  ASSERT_TRUE(first.ok()) << first.status();
  const auto phases = read_json(dir_ / "out" / "phases.json");
  ASSERT_EQ(phases.size(), 3u);
  for (const auto& p : phases) {
    ASSERT_TRUE(p.contains("async")) << p;
    const int launched = p["async"]["launched_before"].get<int>();
    EXPECT_EQ(launched, p["iteration"].get<int>() + 1);
    EXPECT_EQ(p["async"]["joined_before"].get<int>(), launched + 10);
    EXPECT_GE(p["async"]["generation_seconds"].get<double>(), p["async"]["waited_seconds"].get<double>());
    EXPECT_GT(p["admitted"].get<int>(), 0);
    EXPECT_FALSE(p["active"].empty());
  }
  RunOptions again = run;
  again.out_dir = dir_ / "again";
  auto second = run_pipeline(again, nullptr, [](const std::string&) {});
  ASSERT_TRUE(second.ok()) << second.status();
  // The schedule does not depend on timing. (The metrics may differ in the last digits: the generator's thread
  // shares the CPU's parallel regions with training, whose float sums then split differently.)
  const auto repeated = read_json(dir_ / "again" / "phases.json");
  ASSERT_EQ(repeated.size(), 3u);
  for (size_t k = 0; k < 3; ++k) EXPECT_EQ(repeated[k]["async"]["joined_before"], phases[k]["async"]["joined_before"]);
  EXPECT_NEAR(second->metrics.psnr, first->metrics.psnr, 0.5);

  RunOptions late = options(Variant::kFull, &gen);
  late.config.iterations = 100;
  late.gaps.async_iterations = 50;  // longer than a phase interval
  late.out_dir = dir_ / "late";
  ASSERT_TRUE(run_pipeline(late, nullptr, [](const std::string&) {}).ok());
  const auto cut = read_json(dir_ / "late" / "phases.json");
  ASSERT_EQ(cut.size(), 3u);
  EXPECT_EQ(cut[0]["async"]["joined_before"].get<int>(), cut[1]["async"]["launched_before"].get<int>());
  EXPECT_EQ(cut[1]["async"]["joined_before"].get<int>(), cut[2]["async"]["launched_before"].get<int>());
  EXPECT_EQ(cut[2]["async"]["joined_before"].get<int>(), 101) << "judged when the run ended";

  // Asynchronous phases are the default; 0 is the paper's synchronous schedule, which carries no "async" record.
  EXPECT_EQ(GapsConfig{}.async_iterations, 250);
  RunOptions sync = options(Variant::kFull, &gen);
  sync.gaps.async_iterations = 0;
  sync.out_dir = dir_ / "sync";
  ASSERT_TRUE(run_pipeline(sync, nullptr, [](const std::string&) {}).ok());
  for (const auto& p : read_json(dir_ / "sync" / "phases.json")) EXPECT_FALSE(p.contains("async")) << p;
}

// The pseudo-views kept for inspection are written in the background: every one is on disk when the run ends, and
// one that cannot be written fails the run, with phases.json kept.
TEST_F(GapsTrainingTest, InspectionImagesAreAllWrittenAndAFailedWriteFailsTheRun) {
  EchoGenerator gen(0.05);
  auto written = run_pipeline(options(Variant::kFull, &gen), nullptr, [](const std::string&) {});
  ASSERT_TRUE(written.ok()) << written.status();
  std::vector<std::filesystem::path> images;
  for (const auto& phase : read_json(dir_ / "out" / "phases.json"))
    for (const auto& s : phase["selection"])
      images.push_back(dir_ / "out" / kPseudoViewsFolder /
                       pseudo_view_file(phase["phase"].get<int>(), s["id"].get<int>(), s["admitted"].get<bool>()));
  ASSERT_EQ(images.size(), 8u);
  for (const auto& image : images) EXPECT_TRUE(std::filesystem::is_regular_file(image)) << image;

  // The same run (CPU runs repeat bit for bit) into a folder where the last phase's last image is a folder.
  RunOptions blocked = options(Variant::kFull, &gen);
  blocked.out_dir = dir_ / "blocked";
  const std::filesystem::path in_the_way = blocked.out_dir / std::filesystem::relative(images.back(), dir_ / "out");
  std::filesystem::create_directories(in_the_way);
  auto failed = run_pipeline(blocked, nullptr, [](const std::string&) {});
  ASSERT_FALSE(failed.ok());
  EXPECT_TRUE(absl::StrContains(failed.status().message(), in_the_way.filename().string())) << failed.status();
  EXPECT_TRUE(std::filesystem::exists(blocked.out_dir / "phases.json"));
}

// Each phase says where its time went: the sections in the order they run, the generator's own stages as it
// reported them; the adaptation, made at the run's first step, is recorded with the first phase only.
TEST_F(GapsTrainingTest, PhasesRecordTheirTimeBySectionAndTheGeneratorsStages) {
  EchoGenerator gen(0.05);
  auto r = run_pipeline(options(Variant::kFull, &gen), nullptr, [](const std::string&) {});
  ASSERT_TRUE(r.ok()) << r.status();
  const auto phases = read_json(dir_ / "out" / "phases.json");
  ASSERT_EQ(phases.size(), 2u);
  for (size_t k = 0; k < phases.size(); ++k) {
    const auto& seconds = phases[k]["seconds"];
    for (const char* section : {"references", "scoring", "renders", "generation", "admission", "inspection"}) {
      ASSERT_TRUE(seconds.contains(section)) << k << " " << section << " " << seconds;
      EXPECT_GE(seconds[section].get<double>(), 0.0);
    }
    EXPECT_FALSE(seconds.contains("adaptation")) << "adapted before the phase: " << seconds;
    EXPECT_EQ(phases[k].contains("early_adaptation"), k == 0) << phases[k];
    EXPECT_DOUBLE_EQ(phases[k]["generator_stages"]["echo"].get<double>(), 0.25 * (k + 1));
  }
}

// The generator is adapted once, at the run's first step rather than at the first phase (a worker pool then
// trains its LoRA while the model trains), with the views of the model as it is then; a run too short for any
// phase adapts nothing.
TEST_F(GapsTrainingTest, TheGeneratorIsAdaptedAtTheFirstStepOnlyWhenAPhaseWillCome) {
  EchoGenerator gen(0.05);
  auto r = run_pipeline(options(Variant::kFull, &gen), nullptr, [](const std::string&) {});
  ASSERT_TRUE(r.ok()) << r.status();
  EXPECT_EQ(gen.adaptations, 1);
  EXPECT_EQ(gen.generations_before_adapting, 0);
  EXPECT_EQ(gen.adapted_views, 3);
  const auto phases = read_json(dir_ / "out" / "phases.json");
  ASSERT_FALSE(phases.empty());
  EXPECT_EQ(phases[0]["early_adaptation"]["before_iteration"], 1) << phases[0];
  EXPECT_GE(phases[0]["early_adaptation"]["seconds"].get<double>(), 0.0);

  EchoGenerator idle(0.05);
  RunOptions short_run = options(Variant::kFull, &idle);
  short_run.out_dir = dir_ / "short";
  short_run.config.iterations = short_run.gaps.warmup_iterations;  // ends before the first phase
  auto s = run_pipeline(short_run, nullptr, [](const std::string&) {});
  ASSERT_TRUE(s.ok()) << s.status();
  EXPECT_EQ(idle.adaptations, 0);
  EXPECT_EQ(idle.calls, 0);
}

// What the generator could not honour goes into each phase's entry (the adaptation's into the first phase's
// only) and, once per distinct note, into the run log.
TEST_F(GapsTrainingTest, GeneratorNotesGoToThePhaseEntriesAndOnceToTheRunLog) {
  EchoGenerator gen(0.05);
  gen.adapt_notes = {"no LoRA here"};
  gen.generate_notes = {"no IP-Adapter here"};
  std::vector<std::string> log;
  auto r = run_pipeline(options(Variant::kFull, &gen), nullptr, [&](const std::string& line) { log.push_back(line); });
  ASSERT_TRUE(r.ok()) << r.status();
  const auto phases = read_json(dir_ / "out" / "phases.json");
  ASSERT_EQ(phases.size(), 2u);
  EXPECT_EQ(phases[0]["generator_notes"], nlohmann::json({"no LoRA here", "no IP-Adapter here"}));
  EXPECT_EQ(phases[1]["generator_notes"], nlohmann::json({"no IP-Adapter here"}));
  std::vector<std::string> note_lines;
  for (const auto& line : log)
    if (line.find("generator note") != std::string::npos) note_lines.push_back(line);
  EXPECT_EQ(note_lines, (std::vector<std::string>{"generator note (phase 0): no LoRA here",
                                                  "generator note (phase 0): no IP-Adapter here"}));
}

TEST_F(GapsTrainingTest, GarbageIsRejectedByTheAdmissionGate) {
  EchoGenerator gen(1.0);  // flat grey: far from the render wherever the scene has contrast
  auto o = options(Variant::kFull, &gen);
  o.gaps.admit_max_residual = 0.05;
  auto r = run_pipeline(o, nullptr, [](const std::string&) {});
  ASSERT_TRUE(r.ok()) << r.status();
  for (const auto& p : read_json(dir_ / "out" / "phases.json")) {
    EXPECT_EQ(p["admitted"].get<int>(), 0);
    for (const auto& s : p["selection"]) EXPECT_NE(s["reason"].get<std::string>(), "");
  }
}

TEST_F(GapsTrainingTest, NoGapsGeneratesPairMidpointsOnceWithoutGate) {
  EchoGenerator gen(1.0);
  auto r = run_pipeline(options(Variant::kNoGaps, &gen), nullptr, [](const std::string&) {});
  ASSERT_TRUE(r.ok()) << r.status();
  EXPECT_EQ(gen.calls, 1);
  const auto phases = read_json(dir_ / "out" / "phases.json");
  ASSERT_EQ(phases.size(), 1u);
  EXPECT_EQ(phases[0]["selection"].size(), 3u);  // 3 training views -> 3 pairs
  // Each pseudo-view's camera (cameras.json's layout) sits halfway between its pair's training cameras.
  const auto cameras = read_cameras_json(dir_ / "out" / "cameras.json");
  ASSERT_TRUE(cameras.ok()) << cameras.status();
  std::set<std::pair<int, int>> pairs;
  for (const auto& s : phases[0]["selection"]) {
    EXPECT_DOUBLE_EQ(s["alpha"].get<double>(), 0.5);
    EXPECT_TRUE(s["admitted"].get<bool>());
    const int i = s["pair"][0].get<int>(), j = s["pair"][1].get<int>();
    pairs.insert({i, j});
    const auto pseudo = parse_camera_json(s["camera"], "selection");
    ASSERT_TRUE(pseudo.ok()) << pseudo.status();
    EXPECT_EQ(pseudo->split, "pseudo");
    const Eigen::Vector3d midpoint = 0.5 * ((*cameras)[i].camera.center() + (*cameras)[j].camera.center());
    EXPECT_LT((pseudo->camera.center() - midpoint).norm(), 1e-6 * (1 + midpoint.norm()));
  }
  EXPECT_EQ(pairs.size(), 3u);
}

// no-gaps drops the gate, not the uncertainty-weighted loss: an admitted view's weight map is eq:pseudo_loss's,
// w_PLW · α(p) · (1 - λ_u u(p) / max u), whose lowest value is at most w_PLW (1 - λ_u), where u peaks.
TEST_F(GapsTrainingTest, NoGapsTrainsWithUncertaintyWeights) {
  EchoGenerator gen(1.0);  // flat grey: a residual that varies over the image
  RunOptions o = options(Variant::kNoGaps, &gen);
  o.checkpoint_dir = dir_ / "checkpoint";
  int polls = 0;
  o.should_stop = [&] { return ++polls > 45; };  // after phase 0 (iteration 30): the checkpoint holds its views
  auto r = run_pipeline(o, nullptr, [](const std::string&) {});
  ASSERT_EQ(r.status().code(), absl::StatusCode::kCancelled) << r.status();
  const auto state = read_json(dir_ / "checkpoint" / "state.json");
  const auto& admitted = state["method"]["admitted"];
  ASSERT_EQ(admitted.size(), 3u);
  const double w_plw = o.gaps.pseudo_loss_weight, lambda = o.gaps.uncertainty_lambda;
  for (const auto& a : admitted) {
    auto weight = read_npy(dir_ / "checkpoint" / ("admitted_" + std::to_string(a["id"].get<int>()) + "_weight.npy"));
    ASSERT_TRUE(weight.ok()) << weight.status();
    EXPECT_LE(weight->data.max().item<double>(), w_plw + 1e-6);
    EXPECT_GE(weight->data.min().item<double>(), 0.0);
    EXPECT_LE(weight->data.min().item<double>(), w_plw * (1 - lambda) + 1e-4);
  }
}

// C_hist must remember rejected generations: every candidate's logged C_gen is eq:c_gen on the mean of the
// variances its earlier generations logged, and a view rejected with a high variance scores lower next phase.
TEST_F(GapsTrainingTest, ARejectedViewLosesConfidenceNextPhase) {
  ContraryGenerator gen;
  RunOptions o = options(Variant::kFull, &gen);
  o.gaps.admit_max_residual = 0.3;    // every contrary view (residual >= 0.5) is rejected
  o.gaps.hist_variance_scale = 0.25;  // and its variance (>= 0.25) leaves it no historical confidence
  auto r = run_pipeline(o, nullptr, [](const std::string&) {});
  ASSERT_TRUE(r.ok()) << r.status();
  const auto phases = read_json(dir_ / "out" / "phases.json");
  ASSERT_EQ(phases.size(), 2u);
  EXPECT_EQ(phases[0]["admitted"].get<int>(), 0);
  std::map<int, std::vector<double>> generated;  // id -> variances logged by earlier phases
  for (const auto& s : phases[0]["selection"]) {
    EXPECT_FALSE(s["admitted"].get<bool>());
    EXPECT_GE(s["uncertainty_variance"].get<double>(), 0.25);
    generated[s["id"].get<int>()].push_back(s["uncertainty_variance"].get<double>());
  }
  ASSERT_FALSE(generated.empty());
  const double gamma = o.gaps.gamma_hist;
  int rescored = 0;
  for (const auto& cand : phases[1]["candidates"]) {
    const double c_model = cand["c_model"].get<double>(), c_gen = cand["c_gen"].get<double>();
    const auto it = generated.find(cand["id"].get<int>());
    if (it == generated.end()) {
      EXPECT_DOUBLE_EQ(c_gen, c_model) << cand;
      continue;
    }
    double mean = 0;
    for (double v : it->second) mean += v / static_cast<double>(it->second.size());
    const double c_hist = 1.0 - std::min(1.0, mean / o.gaps.hist_variance_scale);
    EXPECT_NEAR(c_gen, (1 - gamma) * c_model + gamma * c_hist, 1e-12) << cand;
    EXPECT_LT(c_gen, c_model) << cand;
    ++rescored;
  }
  EXPECT_EQ(rescored, static_cast<int>(generated.size()));  // tier 0 still: every generated view is scored
}

TEST_F(GapsTrainingTest, MethodVariantsNeedAGenerator) {
  auto r = run_pipeline(options(Variant::kFull, nullptr), nullptr, [](const std::string&) {});
  ASSERT_FALSE(r.ok());
  EXPECT_NE(std::string(r.status().message()).find("generator"), std::string::npos);
}

// The real scene with the reproject backend: two phases on fern (3 views, -r 8), views admitted, finite.
TEST(GapsOnFern, TwoPhasesWithTheReprojectBackendAdmitAndStayFinite) {
  const std::filesystem::path fern = std::filesystem::path(GAPS_DATA_DIR) / "llff" / "fern";
  if (!std::filesystem::exists(fern)) GTEST_SKIP() << "benchmark data not found at " << fern;
  const auto out = std::filesystem::path(::testing::TempDir()) / "gaps_fern_reproject";
  test::remove_tree(out);
  auto generator = make_generator("reproject", "");
  ASSERT_TRUE(generator.ok()) << generator.status();
  RunOptions o;
  o.scene_dir = fern;
  o.out_dir = out;
  o.views = 3;
  o.resolution = 8;
  o.init = "random";
  o.random_points = 3000;
  o.config.iterations = 120;
  o.variant = Variant::kFull;
  o.generator = generator->get();
  o.gaps.warmup_iterations = 40;
  o.gaps.phase_interval = 40;
  o.gaps.n_active = 4;
  std::vector<double> losses;
  auto r = run_pipeline(
      o, [&](const TrainProgress& p) { losses.push_back(p.loss); }, [](const std::string&) {});
  ASSERT_TRUE(r.ok()) << r.status();
  for (double l : losses) EXPECT_TRUE(std::isfinite(l));
  EXPECT_TRUE(std::isfinite(r->metrics.psnr));
  const auto phases = read_json(out / "phases.json");
  ASSERT_EQ(phases.size(), 2u);  // at iterations 40 and 80
  int admitted = 0;
  for (const auto& p : phases) admitted += p["admitted"].get<int>();
  EXPECT_GT(admitted, 0);
  test::remove_tree(out);
}

TEST(Variants, ParseAndName) {
  for (const char* n : {"vanilla", "full", "no-gaps", "no-dropgaussian"}) {
    auto v = parse_variant(n);
    ASSERT_TRUE(v.ok());
    EXPECT_EQ(variant_name(*v), n);
  }
  EXPECT_FALSE(parse_variant("fancy").ok());
}

}  // namespace
}  // namespace gaps

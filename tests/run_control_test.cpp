// Run control hooks used by the trainer service: a generator that cannot be reached skips diffusion
// phases (reported to the phase observer) instead of failing the run, any other generator error still
// fails it, should_stop ends a run with CANCELLED while keeping the model and checkpointing it, and a
// stopped run resumes from that checkpoint.
#include <algorithm>
#include <fstream>
#include <map>
#include <vector>

#include <ATen/ATen.h>
#include <gtest/gtest.h>

#include "common/io_util.h"
#include "gs_trainer/pipeline.h"
#include "gs_trainer/synthetic.h"
#include "tests/synthetic_run.h"
#include "tests/test_util.h"

namespace gaps {
namespace {

// Fails every call with the given status; counts the calls.
class FailingGenerator : public Generator {
 public:
  explicit FailingGenerator(absl::Status error) : error_(std::move(error)) {}
  std::string name() const override { return "failing (test)"; }
  absl::Status adapt(const std::vector<ReferenceView>&, const std::optional<SceneAdaptation>&) override {
    return absl::OkStatus();
  }
  absl::StatusOr<std::vector<at::Tensor>> generate(const std::vector<GenerationRequest>&) override {
    ++calls;
    return error_;
  }
  int calls = 0;

 private:
  absl::Status error_;
};

// Returns the render it was given: always admitted.
class EchoGenerator : public Generator {
 public:
  std::string name() const override { return "echo (test)"; }
  absl::Status adapt(const std::vector<ReferenceView>&, const std::optional<SceneAdaptation>&) override {
    return absl::OkStatus();
  }
  absl::StatusOr<std::vector<at::Tensor>> generate(const std::vector<GenerationRequest>& requests) override {
    ++calls;
    std::vector<at::Tensor> out;
    for (const auto& r : requests) out.push_back(r.render_rgb);
    return out;
  }
  int calls = 0;
};

struct RunControlTest : test::TempDirTest {
  RunOptions options(Generator* generator) {
    RunOptions o = test::short_run(dir_, generator ? Variant::kFull : Variant::kVanilla, generator);
    o.random_points = 1000;
    o.config.iterations = 70;
    o.gaps.n_active = 2;
    o.save_renders = false;
    return o;
  }
  void SetUp() override {
    test::TempDirTest::SetUp();
    test::write_small_scene(dir_, 48, 36);
  }
};

TEST_F(RunControlTest, UnreachableGeneratorSkipsPhasesAndTrainingCompletes) {
  FailingGenerator generator(absl::UnavailableError("no diffusion worker answered"));
  RunOptions o = options(&generator);
  std::vector<std::pair<std::string, nlohmann::json>> seen;
  o.on_phase = [&](const std::string& what, const nlohmann::json& entry) { seen.emplace_back(what, entry); };
  auto r = run_pipeline(o, nullptr, [](const std::string&) {});
  ASSERT_TRUE(r.ok()) << r.status();
  EXPECT_EQ(generator.calls, 2);  // phases at iterations 30 and 60
  ASSERT_EQ(seen.size(), 4u);
  for (int phase = 0; phase < 2; ++phase) {
    EXPECT_EQ(seen[2 * phase].first, "started");
    EXPECT_EQ(seen[2 * phase + 1].first, "skipped");
    EXPECT_EQ(seen[2 * phase + 1].second["phase"], phase);
    EXPECT_NE(seen[2 * phase + 1].second["skip_reason"].get<std::string>().find("no diffusion worker"),
              std::string::npos);
  }
  std::ifstream f(dir_ / "out" / "phases.json");
  const auto phases = nlohmann::json::parse(f);
  ASSERT_EQ(phases.size(), 2u);
  for (const auto& p : phases) EXPECT_TRUE(p["skipped"].get<bool>());
  EXPECT_TRUE(std::filesystem::exists(dir_ / "out" / "metrics.json"));
}

TEST_F(RunControlTest, OtherGeneratorErrorsStillFailTheRun) {
  FailingGenerator generator(absl::InternalError("backend crashed"));
  auto r = run_pipeline(options(&generator), nullptr, [](const std::string&) {});
  ASSERT_FALSE(r.ok());
  EXPECT_EQ(r.status().code(), absl::StatusCode::kInternal);
}

TEST_F(RunControlTest, ShouldStopCancelsAndKeepsTheModel) {
  RunOptions o = options(nullptr);
  int polls = 0, started = 0;
  o.should_stop = [&] { return ++polls > 25; };
  o.on_training_started = [&] { ++started; };
  int last_iteration = 0;
  auto r = run_pipeline(
      o, [&](const TrainProgress& p) { last_iteration = p.iteration; }, [](const std::string&) {});
  ASSERT_FALSE(r.ok());
  EXPECT_EQ(r.status().code(), absl::StatusCode::kCancelled);
  EXPECT_EQ(started, 1);
  EXPECT_LE(last_iteration, 25);
  EXPECT_TRUE(std::filesystem::exists(dir_ / "out" / "point_cloud.ply"));
  EXPECT_FALSE(std::filesystem::exists(dir_ / "out" / "metrics.json"));
}

// A stop during the initialisation (PatchMatch here) ends the run there: CANCELLED before training began,
// with neither a model nor a checkpoint to keep.
TEST_F(RunControlTest, AStopDuringTheInitialisationCancelsBeforeTraining) {
  RunOptions o = options(nullptr);
  o.init = "mvs";
  o.init_cache_dir = dir_ / "init_cache";
  o.checkpoint_dir = dir_ / "checkpoint";
  int polls = 0, started = 0;
  o.should_stop = [&] { return ++polls == 3; };  // in PatchMatch's first sweep
  o.on_training_started = [&] { ++started; };
  std::vector<std::string> log;
  auto r = run_pipeline(o, nullptr, [&](const std::string& line) { log.push_back(line); });
  EXPECT_EQ(r.status().code(), absl::StatusCode::kCancelled) << r.status();
  EXPECT_EQ(r.status().message(), "PatchMatch stopped at view 0");
  EXPECT_EQ(polls, 3);
  EXPECT_EQ(started, 0);
  EXPECT_FALSE(std::filesystem::exists(dir_ / "out" / "point_cloud.ply"));
  EXPECT_FALSE(std::filesystem::exists(dir_ / "checkpoint"));
}

// A stop checkpoints where the run is (a crash leaves only the phase checkpoints: see services_e2e_test).
TEST_F(RunControlTest, AStoppedRunResumesFromWhereItStopped) {
  EchoGenerator generator;
  RunOptions o = options(&generator);
  o.checkpoint_dir = dir_ / "checkpoint";
  std::vector<int> checkpoints;
  o.on_checkpoint = [&](int iteration) { checkpoints.push_back(iteration); };
  int polls = 0;
  o.should_stop = [&] { return ++polls > 45; };
  auto stopped = run_pipeline(o, nullptr, [](const std::string&) {});
  ASSERT_EQ(stopped.status().code(), absl::StatusCode::kCancelled) << stopped.status();
  // The start of phase 0 (before iteration 30), then the stop after iteration 45.
  EXPECT_EQ(checkpoints, (std::vector<int>{29, 45}));

  o.should_stop = nullptr;
  std::vector<std::string> log;
  std::vector<int> reported;
  auto resumed = run_pipeline(
      o, [&](const TrainProgress& p) { reported.push_back(p.iteration); },
      [&](const std::string& line) { log.push_back(line); });
  ASSERT_TRUE(resumed.ok()) << resumed.status();
  EXPECT_NE(std::find(log.begin(), log.end(), "resumed from the checkpoint at iteration 45"), log.end());
  ASSERT_FALSE(reported.empty());
  EXPECT_EQ(reported.front(), 50);  // training went on from iteration 45
  EXPECT_EQ(reported.back(), 70);
  EXPECT_EQ(generator.calls, 1 + 1);  // phase 0 before the stop, phase 1 after the resume
  EXPECT_EQ(checkpoints, (std::vector<int>{29, 45, 59}));
  std::ifstream f(dir_ / "out" / "phases.json");
  const auto phases = nlohmann::json::parse(f);
  ASSERT_EQ(phases.size(), 2u);
  EXPECT_EQ(phases[0]["phase"], 0);
  EXPECT_EQ(phases[1]["phase"], 1);
}

// A time-based checkpoint is due once its seconds have passed since the last save: with a microsecond every
// iteration saves (none takes less), with a day none does (the end of a run saves nothing).
TEST_F(RunControlTest, TimedCheckpointsFollowTheClock) {
  for (const double seconds : {1e-6, 86400.0}) {
    RunOptions o = options(nullptr);
    o.checkpoint_dir = dir_ / "checkpoint";
    o.checkpoint_every_seconds = seconds;
    std::vector<int> checkpoints;
    o.on_checkpoint = [&](int iteration) { checkpoints.push_back(iteration); };
    auto r = run_pipeline(o, nullptr, [](const std::string&) {});
    ASSERT_TRUE(r.ok()) << r.status();
    std::vector<int> expected;
    if (seconds < 1)
      for (int it = 1; it < o.config.iterations; ++it) expected.push_back(it);
    EXPECT_EQ(checkpoints, expected) << seconds << " s";
    remove_tree(dir_ / "checkpoint");
    remove_tree(dir_ / "out");
  }
}

// C_hist's history (every phase's uncertainty variance per generated view) is saved and read back: after the
// resume, phase 1 scores the views phase 0 generated with it (eq:c_gen), as an uninterrupted run would.
TEST_F(RunControlTest, TheUncertaintyHistorySurvivesAResume) {
  EchoGenerator generator;
  RunOptions o = options(&generator);
  o.checkpoint_dir = dir_ / "checkpoint";
  int polls = 0;
  o.should_stop = [&] { return ++polls > 45; };
  ASSERT_EQ(run_pipeline(o, nullptr, [](const std::string&) {}).status().code(), absl::StatusCode::kCancelled);
  auto state = read_file_bytes(dir_ / "checkpoint" / "state.json");
  ASSERT_TRUE(state.ok());
  const auto method = nlohmann::json::parse(*state)["method"];
  ASSERT_EQ(method["log"].size(), 1u);
  std::map<int, std::vector<double>> logged;  // what phase 0 generated, from its log
  for (const auto& s : method["log"][0]["selection"])
    logged[s["id"].get<int>()].push_back(s["uncertainty_variance"].get<double>());
  std::map<int, std::vector<double>> saved;
  for (const auto& e : method["uncertainty_history"]) saved[e[0].get<int>()] = e[1].get<std::vector<double>>();
  ASSERT_FALSE(logged.empty());
  EXPECT_EQ(saved, logged);

  o.should_stop = nullptr;
  ASSERT_TRUE(run_pipeline(o, nullptr, [](const std::string&) {}).ok());
  std::ifstream f(dir_ / "out" / "phases.json");
  const auto phases = nlohmann::json::parse(f);
  ASSERT_EQ(phases.size(), 2u);
  int rescored = 0;
  for (const auto& cand : phases[1]["candidates"]) {
    const auto it = saved.find(cand["id"].get<int>());
    if (it == saved.end()) continue;
    const double c_hist = 1.0 - std::min(1.0, it->second[0] / o.gaps.hist_variance_scale);
    const double gamma = o.gaps.gamma_hist;
    EXPECT_NEAR(cand["c_gen"].get<double>(), (1 - gamma) * cand["c_model"].get<double>() + gamma * c_hist, 1e-12)
        << cand;
    ++rescored;
  }
  EXPECT_EQ(rescored, static_cast<int>(saved.size()));
}

TEST_F(RunControlTest, ACheckpointRestoresTheModelAndIteration) {
  EchoGenerator generator;
  RunOptions o = options(&generator);
  o.checkpoint_dir = dir_ / "checkpoint";
  o.config.iterations = 40;  // one phase, at 30
  ASSERT_TRUE(run_pipeline(o, nullptr, [](const std::string&) {}).ok());
  auto state = read_file_bytes(dir_ / "checkpoint" / "state.json");
  ASSERT_TRUE(state.ok());
  const auto j = nlohmann::json::parse(*state);
  EXPECT_EQ(j["iteration"], 29);
  EXPECT_EQ(j["method"]["log"].size(), 0u);  // saved before phase 0 ran
  EXPECT_TRUE(std::filesystem::exists(dir_ / "checkpoint" / "model_means.npy"));
  EXPECT_FALSE(std::filesystem::exists(dir_ / "checkpoint.partial"));
  std::filesystem::remove(dir_ / "checkpoint" / "model_means.npy");
  auto broken = run_pipeline(o, nullptr, [](const std::string&) {});
  ASSERT_FALSE(broken.ok());
  EXPECT_NE(broken.status().message().find("model_means"), std::string_view::npos) << broken.status();
}

}  // namespace
}  // namespace gaps

// The command lines as a user meets them: the real gaps, gaps-trainer and gaps-worker binaries, run on
// mistakes (each must end in one line naming the problem, with its documented exit code, before any
// expensive work and never in an abort), on the conventions they share (flag spellings, short forms,
// suggestions, per-command help), on a run stopped by SIGINT and resumed, and against what README.md and the
// documentation pages with command lines say.
#include <signal.h>

#include <fstream>
#include <map>
#include <regex>
#include <set>
#include <thread>

#include <ATen/Context.h>
#include <gtest/gtest.h>
#include <nlohmann/json.hpp>

#include "absl/strings/match.h"
#include "absl/strings/str_join.h"
#include "absl/strings/str_split.h"
#include "common/cli/command_line.h"
#include "gs_trainer/init/patchmatch.h"
#include "gs_trainer/synthetic.h"
#include "tests/process_util.h"
#include "tests/synthetic_run.h"
#include "tests/test_util.h"

namespace gaps {
namespace {

using test::contains;
using test::read_json;
using test::read_text;

namespace fs = std::filesystem;
using test::Process;

const std::string kGaps = GAPS_CLI_BIN;
const std::string kTrainer = GAPS_TRAINER_BIN;
const std::string kWorker = GAPS_WORKER_BIN;
const fs::path kFern = fs::path(GAPS_DATA_DIR) / "llff" / "fern";
const fs::path kSourceDir = fs::path(GAPS_TEST_SCRIPTS_DIR) / "..";
// The exit-status table lives in docs/usage.md; these pages name flags and show command lines.
const std::string kUsageDoc = "docs/usage.md";
const std::vector<std::string> kDocsWithFlags = {
    "README.md",       "docs/usage.md",  "docs/services.md",   "docs/initialisation.md",
    "docs/results.md", "docs/status.md", "docs/development.md"};
// Those whose code blocks must hold at least one gaps, gaps-trainer or gaps-worker command line.
const std::set<std::string> kDocsWithCommandLines = {"README.md", "docs/usage.md", "docs/services.md",
                                                     "docs/initialisation.md"};
const std::vector<std::string> kCommands = {"train", "init",    "demo", "submit", "watch",  "list", "cancel",
                                            "fetch", "options", "view", "export", "render", "eval"};

// The flags a --help text lists (names with underscores, as absl has them) and its short forms ("r").
struct HelpFlags {
  std::set<std::string> names;
  std::set<std::string> short_names;
};

HelpFlags flags_in_help(const std::string& help) {
  HelpFlags flags;
  const std::regex line("^  ((?:-[a-z], )*)--([a-z0-9-]+)");
  const std::regex short_name("-([a-z]), ");
  for (absl::string_view l : absl::StrSplit(help, '\n')) {
    const std::string s(l);
    std::smatch m;
    if (!std::regex_search(s, m, line)) continue;
    std::string name = m[2];
    std::replace(name.begin(), name.end(), '-', '_');
    flags.names.insert(name);
    const std::string shorts = m[1];
    for (std::sregex_iterator it(shorts.begin(), shorts.end(), short_name), end; it != end; ++it)
      flags.short_names.insert((*it)[1]);
  }
  return flags;
}

struct Cli : test::TempDirTest {
  // A small synthetic scene (9 images, 64x48): enough for quick runs without the benchmark data.
  fs::path scene() {
    if (!fs::exists(dir_ / "scene")) test::write_small_scene(dir_, 64, 48, 9);
    return dir_ / "scene";
  }
  // `gaps train` on the synthetic scene for a few iterations, with `extra` flags.
  std::pair<int, std::string> quick_train(const std::string& out, const std::string& extra = "") {
    return test::run_command(kGaps + " train --scene " + scene().string() + " --out " + out +
                             " --resolution 1 --iterations 20 --init random --random-points 300 --device cpu "
                             "--eval-every 0 --report=false " +
                             extra);
  }
  std::string help(const std::string& command) {
    auto [code, out] = test::run_command(command + " --help");
    EXPECT_EQ(code, 0) << command << ": " << out;
    return out;
  }
};

// An exit code and a message, never an abort or a stack trace.
void expect_failure(const std::pair<int, std::string>& result, int code, const std::string& message) {
  EXPECT_EQ(result.first, code) << result.second;
  EXPECT_TRUE(contains(result.second, message)) << "expected '" << message << "' in:\n" << result.second;
  EXPECT_FALSE(contains(result.second, "internal error")) << result.second;
  EXPECT_FALSE(contains(result.second, "terminate called")) << result.second;
}

TEST_F(Cli, AnUnusableOutputFolderIsAUsageErrorBeforeAnyWork) {
  std::ofstream(dir_ / "a_file") << "x";
  for (const auto& [out, message] : std::vector<std::pair<std::string, std::string>>{
           {"/proc/gaps-out", "cannot create the output folder"},
           {(dir_ / "a_file").string(), "the output folder is a file"},
           {(dir_ / "a_file" / "below").string(), "cannot create the output folder"}}) {
    const auto result = quick_train(out);
    expect_failure(result, 2, out + ": " + message);
    EXPECT_FALSE(contains(result.second, "initial points")) << result.second;  // nothing was initialised
  }
}

TEST_F(Cli, UnknownOrAbsentDevicesAreUsageErrorsInEveryProgram) {
  expect_failure(quick_train((dir_ / "out").string(), "--device gpu"), 2, "'gpu' is not cpu, cuda or cuda:N");
  if (!at::hasCUDA())
    expect_failure(quick_train((dir_ / "out").string(), "--device cuda"), 2, "no CUDA device is available here");
  expect_failure(
      test::run_command(kTrainer + " --listen 127.0.0.1:0 --data-dir " + (dir_ / "data").string() + " --device gpu"), 2,
      "device 'gpu' is not cpu, cuda or cuda:N");
  expect_failure(test::run_command(kWorker + " --listen 127.0.0.1:0 --device gpu"), 2,
                 "device 'gpu' is not cpu, cuda or cuda:N");
  // A memory cap is for a GPU the process computes on; it is checked before anything loads.
  expect_failure(test::run_command(kWorker + " --listen 127.0.0.1:0 --gpu-memory-gib 8"), 2,
                 "a GPU memory cap needs a CUDA device, not cpu");
  expect_failure(test::run_command(kTrainer + " --listen 127.0.0.1:0 --data-dir " + (dir_ / "data").string() +
                                   " --gpu-memory-gib -1"),
                 2, "GPU memory cap must be a number of GiB >= 0");
}

// The restore backend's weights are the set-up's to make: a worker without them says which command makes them (input
// data, 4); a mistaken option is the user's to fix (usage, 2). Both before it listens.
TEST_F(Cli, ARestoreWorkerWithoutItsWeightsNamesTheSetupCommand) {
  expect_failure(test::run_command(kWorker + " --listen 127.0.0.1:0 --backend restore --backend-options " +
                                   "'{\"weights\": \"/nonexistent/x4.safetensors\"}'"),
                 4, "'/nonexistent/x4.safetensors': run `bash scripts/setup.sh`");
  expect_failure(test::run_command(kWorker + " --listen 127.0.0.1:0 --backend restore --backend-options " +
                                   "'{\"compose\": \"sdxl\"}'"),
                 2, "restore option 'compose' = \"sdxl\": must be none or reproject");
}

// The exit status is docs/usage.md's table: a broken file a flag names is input data (4), a mistake in the flags
// is usage (2), a folder where the job database belongs is input data, not an unreachable service (5).
TEST_F(Cli, ExitCodesFollowTheTable) {
  std::ofstream(dir_ / "broken.ply") << "ply\nformat ascii 1.0\nelement vertex 3\nend_header\n1 2\n";
  expect_failure(test::run_command(kGaps + " train " + scene().string() + " --init-ply " +
                                   (dir_ / "broken.ply").string() + " --iterations 5 --out " + (dir_ / "o").string()),
                 4, "broken.ply");
  fs::create_directories(dir_ / "data" / "jobs.db");
  expect_failure(test::run_command(kTrainer + " --listen 127.0.0.1:0 --data-dir " + (dir_ / "data").string()), 4,
                 "jobs.db is a folder, not a job database");
  std::ofstream(dir_ / "cert.pem") << "x";
  expect_failure(
      test::run_command(kGaps + " list --trainer 127.0.0.1:1 --tls-client-cert " + (dir_ / "cert.pem").string()), 2,
      "a client TLS certificate needs its private key");
}

// Ctrl-C mid-run saves the run; --resume finishes it where an uninterrupted run ends (vanilla restores the
// view order and RNG, so the result matches to the bit here; seed noise would be the tolerance otherwise).
TEST_F(Cli, SigintSavesTheRunAndResumeFinishesItAsAnUninterruptedRunWould) {
  if (!fs::exists(kFern)) GTEST_SKIP() << "benchmark data not found at " << kFern;
  const std::vector<std::string> run = {kGaps,
                                        "train",
                                        "--scene",
                                        kFern.string(),
                                        "-r",
                                        "8",
                                        "--iterations",
                                        "80",
                                        "--init",
                                        "random",
                                        "--random-points",
                                        "400",
                                        "--device",
                                        "cpu",
                                        "--eval-every",
                                        "20",
                                        "--save-every",
                                        "20",
                                        "--report=false",
                                        "--patchmatch-best-views",
                                        "3",
                                        "--fusion-min-views",
                                        "3",
                                        "--sparse-max-image-side",
                                        "64"};
  auto with_out = [&](const fs::path& out) {
    std::vector<std::string> argv = run;
    argv.insert(argv.end(), {"--out", out.string()});
    return argv;
  };
  auto [code, log] = test::run_command(absl::StrJoin(with_out(dir_ / "whole"), " "));
  ASSERT_EQ(code, 0) << log;
  // PatchMatch settings with another method are said to do nothing.
  EXPECT_TRUE(contains(log,
                       "init: --fusion-min-views, --patchmatch-best-views, --sparse-max-image-side not used: the "
                       "points came from random"))
      << log;

  Process stopped(with_out(dir_ / "stopped"), dir_ / "stopped.log");
  const auto deadline = std::chrono::steady_clock::now() + std::chrono::minutes(2);
  while (!contains(stopped.log_text(), "checkpoint at iteration 20") && stopped.running() &&
         std::chrono::steady_clock::now() < deadline)
    std::this_thread::sleep_for(std::chrono::milliseconds(20));
  ASSERT_EQ(stopped.stop(SIGINT, std::chrono::seconds(60)), 130) << stopped.log_text();
  const std::string stop_log = stopped.log_text();
  EXPECT_TRUE(contains(stop_log, "stopped by SIGINT at iteration")) << stop_log;
  EXPECT_TRUE(contains(stop_log, "gaps train --resume " + (dir_ / "stopped").string())) << stop_log;
  EXPECT_TRUE(fs::exists(dir_ / "stopped" / "checkpoint" / "state.json"));
  EXPECT_FALSE(fs::exists(dir_ / "stopped" / "metrics.json"));

  // Only what does not change the run may come with --resume.
  expect_failure(test::run_command(kGaps + " train --resume " + (dir_ / "stopped").string() + " --views 6"), 2,
                 "--views cannot change them");
  std::tie(code, log) = test::run_command(kGaps + " train --resume " + (dir_ / "stopped").string());
  ASSERT_EQ(code, 0) << log;
  EXPECT_TRUE(contains(log, "resumed from the checkpoint at iteration")) << log;
  EXPECT_FALSE(fs::exists(dir_ / "stopped" / "checkpoint"));  // a finished run keeps its results only
  const nlohmann::json whole = read_json(dir_ / "whole" / "metrics.json");
  const nlohmann::json resumed = read_json(dir_ / "stopped" / "metrics.json");
  EXPECT_EQ(resumed["status"], "ok");
  EXPECT_EQ(resumed["iterations"], 80);
  // The initialisation settings travel through the run record to the resumed run's metrics.
  EXPECT_EQ(resumed["init_options"], whole["init_options"]);
  EXPECT_EQ(resumed["init_options"]["patchmatch_best_views"], 3) << resumed["init_options"];
  EXPECT_EQ(resumed["init_options"]["fusion_min_views"], 3) << resumed["init_options"];
  EXPECT_NEAR(resumed["psnr"].get<double>(), whole["psnr"].get<double>(), 1e-6);
  // The curve goes on across the stop: the points before it were kept with the checkpoint.
  ASSERT_EQ(resumed["curve"].size(), whole["curve"].size());
  for (size_t i = 0; i < whole["curve"].size(); ++i)
    EXPECT_NEAR(resumed["curve"][i]["psnr"].get<double>(), whole["curve"][i]["psnr"].get<double>(), 1e-6) << i;
  expect_failure(test::run_command(kGaps + " train --resume " + (dir_ / "stopped").string()), 2,
                 "the run there has ended");
}

// A stop during the initialisation (minutes of PatchMatch on a CPU) ends the run at once: there is nothing to
// save yet, and the first signal must not be left waiting for the first iteration.
TEST_F(Cli, AStopBeforeTrainingBeganEndsTheRunAtOnce) {
  if (!fs::exists(kFern)) GTEST_SKIP() << "benchmark data not found at " << kFern;
  const fs::path out = dir_ / "stopped_in_init";
  Process run({kGaps, "train", "--scene", kFern.string(), "-r", "8", "--iterations", "100", "--init", "mvs",
               "--init-resolution", "4", "--init-cache", (dir_ / "empty_cache").string(), "--device", "cpu", "--out",
               out.string()},
              out.string() + ".log");
  const auto deadline = std::chrono::steady_clock::now() + std::chrono::minutes(2);
  while (!contains(run.log_text(), "init: reading the training views") && run.running() &&
         std::chrono::steady_clock::now() < deadline)
    std::this_thread::sleep_for(std::chrono::milliseconds(20));
  ASSERT_TRUE(run.running()) << run.log_text();
  // PatchMatch on the 1008x756 views takes minutes on a CPU; the run must end well before it would.
  ASSERT_EQ(run.stop(SIGTERM, std::chrono::seconds(30)), 128 + SIGTERM) << run.log_text();
  const std::string log = run.log_text();
  EXPECT_TRUE(contains(log, "stopped before training began, with nothing to save; gaps train --resume " + out.string() +
                                " starts it again"))
      << log;
  EXPECT_FALSE(contains(log, "init: mvs, ")) << log;  // it did not finish the initialisation first
  EXPECT_FALSE(fs::exists(out / "checkpoint"));
  EXPECT_TRUE(fs::exists(out / "run.json"));  // what --resume starts again from
}

TEST_F(Cli, SubmitSendsTheTrainFlagsAndTheJobRecordsThem) {
  Process trainer({kTrainer, "--listen", "127.0.0.1:0", "--data-dir", (dir_ / "data").string(), "--device", "cpu"},
                  dir_ / "trainer.log");
  const int port = trainer.wait_for_port();
  ASSERT_GT(port, 0) << trainer.log_text();
  const std::string at = " --trainer 127.0.0.1:" + std::to_string(port);
  auto [code, out] = test::run_command(
      kGaps + " submit --scene " + scene().string() +
      " --resolution 1 --variant vanilla --iterations 20 --init random --random-points 300 --eval-every 10"
      " --max-gaussians 1234 --gaussians-per-variation 2 --patchmatch-best-views 3 --fusion-max-normal-error 20"
      " --watch --quiet" +
      at);
  ASSERT_EQ(code, 0) << out << trainer.log_text();
  std::smatch m;
  ASSERT_TRUE(std::regex_search(out, m, std::regex("job-[0-9a-f]+"))) << out;
  std::tie(code, out) =
      test::run_command(kGaps + " fetch " + std::string(m[0]) + " -o " + (dir_ / "fetched").string() + at);
  ASSERT_EQ(code, 0) << out;
  const nlohmann::json metrics = read_json(dir_ / "fetched" / "metrics.json");
  EXPECT_EQ(metrics["eval_every"], 10);
  ASSERT_EQ(metrics["curve"].size(), 2u) << metrics["curve"];
  EXPECT_EQ(metrics["curve"][0]["iteration"], 10);
  EXPECT_EQ(metrics["max_gaussians"], 1234);
  EXPECT_EQ(metrics["config"]["gaussians_per_variation"], 2.0);
  // The PatchMatch settings given travel with the job; the others keep the defaults.
  EXPECT_EQ(metrics["init_options"]["patchmatch_best_views"], 3) << metrics["init_options"];
  EXPECT_EQ(metrics["init_options"]["fusion_max_normal_error"], 20.0) << metrics["init_options"];
  EXPECT_EQ(metrics["init_options"]["patchmatch_max_cost"], PatchMatchOptions{}.max_cost) << metrics["init_options"];
  // A flag of gaps train only is refused by submit, naming who takes it.
  expect_failure(test::run_command(kGaps + " submit " + scene().string() + " --init-resolution 2" + at), 2,
                 "--init-resolution is not a flag of gaps submit; gaps train, gaps init take it");
  expect_failure(test::run_command(kGaps + " submit " + scene().string() + " --patchmatch-max-cost 0" + at), 2,
                 "PatchMatch: max_cost must be > 0, got 0");
  // Out-of-range initialisation settings are refused before the scene is read, naming the setting.
  expect_failure(test::run_command(kGaps + " init " + scene().string() + " --patchmatch-best-views 0 --out " +
                                   (dir_ / "refused").string()),
                 2, "PatchMatch: best_views must be >= 1, got 0");
  expect_failure(test::run_command(kGaps + " init " + scene().string() + " --fusion-max-normal-error 0 --out " +
                                   (dir_ / "refused").string()),
                 2, "fusion: max_normal_error_deg must be in (0, 180], got 0");
}

TEST_F(Cli, HelpExitsZeroAndListsExactlyEachCommandsFlags) {
  EXPECT_TRUE(contains(help(kGaps), "exit status:"));
  EXPECT_TRUE(flags_in_help(help(kTrainer)).names.count("data_dir"));
  EXPECT_TRUE(flags_in_help(help(kWorker)).names.count("backend_options"));
  std::map<std::string, HelpFlags> flags;
  for (const std::string& c : kCommands) flags[c] = flags_in_help(help(kGaps + " " + c));
  for (const char* f : {"resume", "save_every", "overwrite", "backend", "eval_every", "lambda_dssim"})
    EXPECT_TRUE(flags["train"].names.count(f)) << f;
  EXPECT_TRUE(flags["train"].short_names.count("r"));
  for (const char* f : {"trainer", "token_file", "tls_ca", "tls_server_name", "tls_client_cert", "tls_client_key",
                        "name", "watch", "eval_every", "max_gaussians", "gaussians_per_variation", "views"})
    EXPECT_TRUE(flags["submit"].names.count(f)) << f;
  EXPECT_TRUE(flags["fetch"].short_names.count("o"));
  EXPECT_TRUE(flags["options"].names.empty());
  // A flag another command lists and this one does not is refused, naming who takes it (one per command).
  for (const std::string& c : kCommands) {
    for (const auto& [other, other_flags] : flags) {
      const auto missing = std::find_if(other_flags.names.begin(), other_flags.names.end(),
                                        [&](const std::string& f) { return !flags[c].names.count(f); });
      if (missing == other_flags.names.end()) continue;
      std::string dashed = *missing;
      std::replace(dashed.begin(), dashed.end(), '_', '-');
      const auto result = test::run_command(kGaps + " " + c + " --" + dashed + "=1");
      expect_failure(result, 2, "--" + dashed + " is not a flag of gaps " + c);
      EXPECT_TRUE(contains(result.second, "gaps " + other)) << result.second;
      break;
    }
  }
}

TEST_F(Cli, FlagSpellingsShortFormsSuggestionsAndStrayArguments) {
  const std::string out = " --out /proc/gaps-out";  // a run that stops at its output folder, after the flags
  const std::string folder_error = "cannot create the output folder";
  expect_failure(test::run_command(kGaps + " train " + scene().string() + " -r 1 --random_points=300" + out), 2,
                 folder_error);
  expect_failure(test::run_command(kGaps + " train -s " + scene().string() + " --no-report -m /proc/gaps-out"), 2,
                 folder_error);
  std::ofstream(dir_ / "a_file") << "x";
  for (const char* spelling : {"--data-dir", "--data_dir"})
    expect_failure(test::run_command(kTrainer + " " + spelling + " " + (dir_ / "a_file").string()), 2,
                   "a file, not a folder");
  expect_failure(test::run_command(kWorker + " --max-batch 0"), 2, "--max-batch must be positive");
  expect_failure(test::run_command(kWorker + " --max-scenes 0"), 2, "--max-scenes must be at least 1");
  // The workers' TLS files are read at start, before the trainer serves anything.
  const auto no_ca = test::run_command(kTrainer + " --data-dir " + (dir_ / "trainer_data").string() +
                                       " --listen 127.0.0.1:0 --workers 127.0.0.1:1 --worker-tls-ca " +
                                       (dir_ / "no_such_ca.pem").string());
  EXPECT_NE(no_ca.first, 0) << no_ca.second;
  EXPECT_TRUE(contains(no_ca.second, "workers' TLS")) << no_ca.second;
  EXPECT_TRUE(contains(no_ca.second, "no_such_ca.pem")) << no_ca.second;
  EXPECT_FALSE(contains(no_ca.second, "serving on")) << no_ca.second;
  // Counts that drive allocations are bounded before anything is allocated: a usage error naming the limit.
  expect_failure(test::run_command(kGaps + " train " + scene().string() +
                                   " --init random --random-points "
                                   "100000000000" +
                                   out),
                 2, "--random-points 100000000000 is over the limit of 67108864 (64 GiB of model");
  expect_failure(test::run_command(kGaps + " train " + scene().string() + " --max-gaussians 100000000000" + out), 2,
                 "max_gaussians");
  expect_failure(test::run_command(kGaps + " train --scene " + scene().string() + " --iteratons 5" + out), 2,
                 "unknown flag --iteratons; did you mean --iterations?");
  expect_failure(test::run_command(kTrainer + " --wokers 127.0.0.1:1"), 2, "did you mean --workers?");
  expect_failure(test::run_command(kGaps + " trian"), 2, "unknown command 'trian'; did you mean train?");
  expect_failure(test::run_command(kGaps + " train " + scene().string() + " extra" + out), 2,
                 "unexpected argument 'extra'");
  expect_failure(test::run_command(kGaps + " list stray"), 2, "unexpected argument 'stray'");
  expect_failure(test::run_command(kGaps + " train --views three"), 2, "--views three: not a valid value");
  // --tryfromenv (how the deployment files lay settings over a command line) takes named flags from FLAGS_*.
  expect_failure(test::run_command("FLAGS_concurrency=many " + kTrainer + " --tryfromenv=workers,concurrency"), 2,
                 "FLAGS_concurrency=many: not a valid value for --concurrency");
  expect_failure(test::run_command(kTrainer + " --tryfromenv=workerz"), 2, "--tryfromenv: gaps-trainer has no flag");
  expect_failure(
      test::run_command("FLAGS_data_dir=" + (dir_ / "a_file").string() + " " + kTrainer + " --tryfromenv=data_dir"), 2,
      "a file, not a folder");
  // train and submit name the scene alike: --scene DIR or the argument.
  expect_failure(test::run_command(kGaps + " submit --scene " + scene().string() + " --trainer 127.0.0.1:1"), 5,
                 "cannot reach a gaps-trainer");
}

TEST_F(Cli, MistakesAreCaughtBeforeLoadingWithMessagesSayingWhatToDo) {
  const std::string out = (dir_ / "out").string();
  auto result = quick_train(out, "--init mvsx");
  expect_failure(result, 2, "--init mvsx: unknown; use auto, mvs, sweep, sparse, random, scene or ply");
  EXPECT_FALSE(contains(result.second, "split:")) << result.second;  // the scene summary comes after the checks
  // 9 images: every 8th (0 and 8) is a test view, 7 remain.
  expect_failure(quick_train(out, "--views 50"), 2, "ask for at most 7 (0: all)");
  fs::create_directories(dir_ / "photos" / "images");
  fs::copy_file(scene() / "images" / "frame_000.png", dir_ / "photos" / "images" / "frame_000.png");
  result = test::run_command(kGaps + " train --scene " + (dir_ / "photos").string() + " --out " + out);
  expect_failure(result, 4, "photos without camera poses");
  const std::string images = (dir_ / "photos" / "images").string(), db = (dir_ / "photos" / "database.db").string();
  for (const std::string& command :
       {"colmap feature_extractor --database_path " + db + " --image_path " + images,
        "colmap exhaustive_matcher --database_path " + db, "colmap mapper --database_path " + db})
    EXPECT_TRUE(contains(result.second, command)) << command << "\n" << result.second;
  result = test::run_command(kGaps + " submit " + scene().string() + " --trainer 127.0.0.1:1");
  expect_failure(result, 5, "cannot reach a gaps-trainer at 127.0.0.1:1");
  EXPECT_FALSE(contains(result.second, "failed to connect to all addresses")) << result.second;
}

TEST_F(Cli, LogsGetPlainProgressLinesAndAReusedFolderKeepsNoStaleFiles) {
  const fs::path out = dir_ / "out";
  auto [code, log] = quick_train(out.string());
  ASSERT_EQ(code, 0) << log;
  EXPECT_FALSE(contains(log, "\r")) << log;  // the output is a pipe, not a terminal
  EXPECT_TRUE(contains(log, "iteration 20/20 (100%)")) << log;
  const nlohmann::json metrics = read_json(out / "metrics.json");
  ASSERT_FALSE(metrics["per_view"].empty());
  EXPECT_TRUE(absl::EndsWith(metrics["per_view"][0]["image"].get<std::string>(), "frame_000.png"))
      << metrics["per_view"];

  expect_failure(quick_train(out.string()), 2, "is not empty");
  std::ofstream(out / "phases.json") << "[]";
  fs::create_directories(out / "pseudo_views" / "phase_0");
  std::ofstream(out / "pseudo_views" / "phase_0" / "0.png") << "x";
  std::ofstream(out / "notes.txt") << "mine";
  std::tie(code, log) = quick_train(out.string(), "--overwrite");
  ASSERT_EQ(code, 0) << log;
  EXPECT_FALSE(fs::exists(out / "phases.json"));
  EXPECT_FALSE(fs::exists(out / "pseudo_views"));
  EXPECT_TRUE(fs::exists(out / "notes.txt"));  // not a gaps output: kept
  EXPECT_TRUE(fs::exists(out / "metrics.json"));

  std::tie(code, log) = test::run_command(kGaps + " --version");
  EXPECT_EQ(code, 0);
  EXPECT_TRUE(std::regex_search(log, std::regex("^gaps [0-9]+\\.[0-9]+\\.[0-9]+ \\(commit [0-9a-f]{7,}"))) << log;
}

TEST_F(Cli, ABudgetBelowTheInitialPointsIsSaidAndTheDemoStartsBelowItsBudget) {
  auto [code, log] = quick_train((dir_ / "out").string(), "--max-gaussians 100");
  ASSERT_EQ(code, 0) << log;
  EXPECT_TRUE(contains(log, "the 300 initial Gaussians already fill the budget of 100 Gaussians")) << log;
  std::tie(code, log) =
      test::run_command(kGaps + " demo --iterations 10 --device cpu --report=false --out " + (dir_ / "demo").string());
  ASSERT_EQ(code, 0) << log;
  std::smatch budget, points;
  ASSERT_TRUE(std::regex_search(log, budget, std::regex("automatic budget: ([0-9]+) Gaussians"))) << log;
  ASSERT_TRUE(std::regex_search(log, points, std::regex("initial points: ([0-9]+)"))) << log;
  EXPECT_LT(std::stoi(points[1]), std::stoi(budget[1])) << log;
  EXPECT_FALSE(contains(log, "already fill the budget")) << log;
}

TEST_F(Cli, TheExitCodesOfTheHelpAreTheUsageDocsTable) {
  const std::string usage = read_text(kSourceDir / kUsageDoc);
  ASSERT_FALSE(usage.empty()) << kUsageDoc << " is missing";
  const std::string overview = help(kGaps);
  const std::regex row("^  ([0-9]+) +(.+)$");
  int rows = 0;
  for (absl::string_view l : absl::StrSplit(overview.substr(overview.find("exit status:")), '\n')) {
    const std::string s(l);
    std::smatch m;
    if (!std::regex_match(s, m, row)) continue;
    ++rows;
    EXPECT_TRUE(contains(usage, "| " + std::string(m[1]) + " | " + std::string(m[2]) + " |"))
        << kUsageDoc << " lacks the row of exit status " << m[1] << ": " << m[2];
  }
  EXPECT_GE(rows, 6);
}

// Every flag README.md and the documentation pages name is one a program takes, and every command line they show
// uses only flags its command takes.
TEST_F(Cli, EveryFlagTheDocsNameIsAcceptedByItsProgram) {
  std::map<std::string, HelpFlags> programs;
  for (const std::string& c : kCommands) programs["gaps " + c] = flags_in_help(help(kGaps + " " + c));
  programs["gaps-trainer"] = flags_in_help(help(kTrainer));
  programs["gaps-worker"] = flags_in_help(help(kWorker));
  std::set<std::string> any = {"help", "version"};  // every program's
  for (const auto& [name, flags] : programs) any.insert(flags.names.begin(), flags.names.end());

  const std::regex flag("(^|[^a-z0-9_-])--([a-z][a-z0-9_-]*)");
  // Command lines in code blocks (continued lines joined): each flag against its own command.
  const std::regex invocation(
      "(gaps-trainer|gaps-worker|gaps (?:train|init|demo|submit|watch|list|cancel|fetch|view|export|render|eval))"
      "((?: +[^ ;|&)#]+)*)");
  const std::regex argument("^(--?)([a-z][a-z0-9_-]*)");
  int total = 0;
  for (const std::string& doc : kDocsWithFlags) {
    const std::string text = read_text(kSourceDir / doc);
    ASSERT_FALSE(text.empty()) << doc << " is missing";
    for (std::sregex_iterator it(text.begin(), text.end(), flag), end; it != end; ++it) {
      std::string name = (*it)[2];
      std::replace(name.begin(), name.end(), '-', '_');
      // --no-report (the gaps CLI) and --noworker-shared-memory (absl's negation of a boolean flag)
      const bool negated = (absl::StartsWith(name, "no_") && any.count(name.substr(3))) ||
                           (absl::StartsWith(name, "no") && any.count(name.substr(2)));
      EXPECT_TRUE(any.count(name) || negated) << doc << " names --" << (*it)[2] << ", which no program takes";
    }
    bool in_code = false;
    std::string logical;
    int checked = 0;
    for (absl::string_view l : absl::StrSplit(text, '\n')) {
      if (absl::StartsWith(l, "```")) {
        in_code = !in_code;
        continue;
      }
      if (!in_code) continue;
      logical += std::string(l);
      if (!logical.empty() && logical.back() == '\\') {
        logical.pop_back();
        continue;
      }
      for (std::sregex_iterator it(logical.begin(), logical.end(), invocation), end; it != end; ++it) {
        const std::string program = (*it)[1];
        const std::string rest = (*it)[2];
        ++checked;
        for (absl::string_view word : absl::StrSplit(rest, ' ', absl::SkipEmpty())) {
          const std::string w(word.substr(0, word.find('=')));
          std::smatch m;
          if (!std::regex_search(w, m, argument)) continue;
          std::string name = m[2];
          std::replace(name.begin(), name.end(), '-', '_');
          const HelpFlags& takes = programs[program];
          EXPECT_TRUE(m[1] == "--" ? takes.names.count(name) > 0 : takes.short_names.count(name) > 0)
              << doc << ": " << program << " does not take " << w << " (in: " << logical << ")";
        }
      }
      logical.clear();
    }
    if (kDocsWithCommandLines.count(doc)) EXPECT_GE(checked, 1) << doc << " shows no command line";
    total += checked;
  }
  EXPECT_GE(total, 15);
}

TEST(CommandLine, ALastLineOfDefenceTurnsExceptionsIntoOneLineAndExitStatusOne) {
  testing::internal::CaptureStderr();
  const int code = cli::run_main("prog", []() -> int { throw std::runtime_error("broken\nframe #0: somewhere"); });
  const std::string err = testing::internal::GetCapturedStderr();
  EXPECT_EQ(code, 1);
  EXPECT_EQ(err, "prog: internal error: broken\n");
}

TEST(CommandLine, ClosestMatchSuggestsTyposAndPrefixesOnly) {
  const std::vector<std::string> names = {"iterations", "init", "init_ply", "views", "resolution"};
  EXPECT_EQ(cli::closest_match("iteratons", names), "iterations");
  EXPECT_EQ(cli::closest_match("veiws", names), "views");
  EXPECT_EQ(cli::closest_match("resol", names), "resolution");
  EXPECT_EQ(cli::closest_match("trainer", names), "");
}

}  // namespace
}  // namespace gaps

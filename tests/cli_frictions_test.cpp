// What a new user meets first with the real gaps and gaps-trainer binaries: a fetch that finds nothing, a
// method run too short for its first phase, the render path of a forward-facing capture, a flag from another
// tool, a run without --out, --quiet, the option table, the help pages and the TLS set-ups that go wrong.
#include <cstdlib>
#include <fstream>
#include <memory>
#include <regex>

#include <gtest/gtest.h>

#include "absl/strings/str_split.h"
#include "gs_trainer/synthetic.h"
#include "tests/process_util.h"
#include "tests/synthetic_run.h"
#include "tests/test_util.h"

namespace gaps {
namespace {

using test::contains;
using test::Process;

namespace fs = std::filesystem;

const std::string kGaps = GAPS_CLI_BIN;
const std::string kTrainer = GAPS_TRAINER_BIN;
const fs::path kFern = fs::path(GAPS_DATA_DIR) / "llff" / "fern";
const fs::path kBonsai = fs::path(GAPS_DATA_DIR) / "mipnerf360" / "bonsai";

struct Frictions : test::TempDirTest {
  // A small synthetic forward-facing scene (9 images, 64x48).
  fs::path scene() {
    if (!fs::exists(dir_ / "scene")) test::write_small_scene(dir_, 64, 48, 9);
    return dir_ / "scene";
  }
  static std::string submit_flags() { return " -r 1 --init random --random-points 300 --eval-every 0"; }
  static std::string quick_flags() { return submit_flags() + " --iterations 20 --device cpu --report=false"; }
  // A gaps-trainer on a free port with `extra` flags; its address in *address.
  std::unique_ptr<Process> trainer(const std::string& name, const std::vector<std::string>& extra,
                                   std::string* address) {
    std::vector<std::string> argv = {kTrainer,   "--listen", "127.0.0.1:0", "--data-dir", (dir_ / name).string(),
                                     "--device", "cpu"};
    argv.insert(argv.end(), extra.begin(), extra.end());
    auto process = std::make_unique<Process>(argv, dir_ / (name + ".log"));
    const int port = process->wait_for_port();
    EXPECT_GT(port, 0) << process->log_text();
    *address = "127.0.0.1:" + std::to_string(port);
    return process;
  }
};

std::string job_id_in(const std::string& text) {
  std::smatch m;
  return std::regex_search(text, m, std::regex("job-[0-9a-f]+")) ? std::string(m[0]) : "";
}

void expect_failure(const std::pair<int, std::string>& result, int code, const std::string& message) {
  EXPECT_EQ(result.first, code) << result.second;
  EXPECT_TRUE(contains(result.second, message)) << "expected '" << message << "' in:\n" << result.second;
}

// 1, and 5's fetch half: a job cancelled while queued has nothing to fetch, and says why with a failure
// status; a finished job is fetched into a folder named after it when no -o is given.
TEST_F(Frictions, FetchSaysAJobCancelledBeforeItRanHasNoArtifactsAndDefaultsToTheJobsFolder) {
  std::string at;
  auto service = trainer("data", {}, &at);
  const std::string remote = " --trainer " + at;
  auto [code, out] = test::run_command(kGaps + " submit " + scene().string() + submit_flags() +
                                       " --iterations 20 --watch --quiet" + remote);
  ASSERT_EQ(code, 0) << out << service->log_text();
  const std::string done = job_id_in(out);
  ASSERT_FALSE(done.empty()) << out;
  std::tie(code, out) = test::run_command("cd " + dir_.string() + " && " + kGaps + " fetch " + done + remote);
  ASSERT_EQ(code, 0) << out;
  EXPECT_TRUE(fs::exists(dir_ / done / "metrics.json")) << out;

  // One job runs at a time: the second waits behind a long first one and is cancelled there.
  std::tie(code, out) =
      test::run_command(kGaps + " submit " + scene().string() + submit_flags() + " --iterations 1000000" + remote);
  const std::string running = job_id_in(out);
  ASSERT_FALSE(running.empty()) << out;
  std::tie(code, out) = test::run_command(kGaps + " submit " + scene().string() + submit_flags() + remote);
  const std::string queued = job_id_in(out);
  ASSERT_FALSE(queued.empty()) << out;
  std::tie(code, out) = test::run_command(kGaps + " cancel " + queued + remote);
  ASSERT_EQ(code, 0) << out;
  ASSERT_TRUE(contains(out, "CANCELLED")) << out;
  const auto fetched = test::run_command(kGaps + " fetch " + queued + " -o " + (dir_ / "nothing").string() + remote);
  expect_failure(fetched, 1, "job " + queued + " has no artifacts: it was cancelled before it ran");
  EXPECT_FALSE(fs::exists(dir_ / "nothing"));
  test::run_command(kGaps + " cancel " + running + remote);
}

// 2: the warning comes when the flags are read, before any work, from train and submit alike.
TEST_F(Frictions, AMethodRunTooShortForItsFirstPhaseIsWarnedNamingTheIterationsNeeded) {
  const std::string warning =
      "warning: --variant full with 50 iterations runs no diffusion phase (the first comes after warmup_iterations "
      "= 1000): give --iterations 1001 or more";
  auto result =
      test::run_command(kGaps + " train " + scene().string() + " --variant full --iterations 50 --out /proc/gaps-out");
  expect_failure(result, 2, warning);
  EXPECT_TRUE(contains(result.second, "cannot create the output folder")) << result.second;
  expect_failure(test::run_command(kGaps + " submit " + scene().string() +
                                   " --variant full --iterations 50 --trainer 127.0.0.1:1"),
                 5, warning);
  result = test::run_command(kGaps + " train " + scene().string() +
                             " --variant full --iterations 50 --warmup-iterations 10 --out /proc/gaps-out");
  EXPECT_FALSE(contains(result.second, "warning")) << result.second;
  result = test::run_command(kGaps + " train " + scene().string() + " --iterations 50 --out /proc/gaps-out");
  EXPECT_FALSE(contains(result.second, "warning")) << result.second;  // vanilla has no phases to miss
}

// 3: without --path, a forward-facing capture gets the spiral and one around the scene the orbit.
TEST_F(Frictions, RenderFollowsTheCaptureWithoutAPath) {
  const fs::path run = dir_ / "run";
  auto [code, out] = test::run_command(kGaps + " train " + scene().string() + quick_flags() + " --out " + run.string());
  ASSERT_EQ(code, 0) << out;
  std::tie(code, out) = test::run_command(kGaps + " render " + run.string() + " --frames 2 --device cpu");
  ASSERT_EQ(code, 0) << out;
  EXPECT_TRUE(contains(out, "path: spiral (the views face one way)")) << out;
  EXPECT_TRUE(fs::exists(run / "render_spiral" / "00001.png")) << out;
  if (!fs::exists(kBonsai)) GTEST_SKIP() << "benchmark data not found at " << kBonsai;
  std::tie(code, out) = test::run_command(kGaps + " render --model " + (run / "point_cloud.ply").string() +
                                          " --scene " + kBonsai.string() + " --views 12 -r 8 --frames 2 --device cpu" +
                                          " --out " + (dir_ / "bonsai").string());
  ASSERT_EQ(code, 0) << out;
  EXPECT_TRUE(contains(out, "path: orbit (the views surround the scene)")) << out;
}

// 4: evaluation needs no flag, and the refusal says so instead of pointing at a flag that does something else.
TEST_F(Frictions, AnEvalFlagIsToldThatTheTestViewsAreAlwaysEvaluated) {
  const auto result = test::run_command(kGaps + " train " + scene().string() + " --eval");
  expect_failure(result, 2,
                 "--eval is not a flag of gaps train and none is needed: every 8th image of the scene is "
                 "always held out as a test view and evaluated when the run ends");
  EXPECT_TRUE(contains(result.second, "--eval-every N")) << result.second;
}

// 5: the scene alone is enough; the run goes to runs/<scene>, said, and a second run there follows the rules.
TEST_F(Frictions, TrainWithoutOutWritesToRunsSceneNameAndSaysSo) {
  const std::string in_dir = "cd " + dir_.string() + " && " + kGaps + " train ";
  auto [code, out] = test::run_command(in_dir + scene().string() + quick_flags());
  ASSERT_EQ(code, 0) << out;
  EXPECT_TRUE(contains(out, "no --out given: the run goes to runs/scene")) << out;
  EXPECT_TRUE(fs::exists(dir_ / "runs" / "scene" / "metrics.json")) << out;
  expect_failure(test::run_command(in_dir + "--scene " + scene().string() + "/" + quick_flags()), 2,
                 "runs/scene is not empty");
  expect_failure(test::run_command(kGaps + " train --iterations 5"), 2, "the scene folder is missing");
}

// 6: --quiet leaves the result in one line.
TEST_F(Frictions, QuietPrintsOnlyTheResultLine) {
  const auto [code, out] = test::run_command(kGaps + " train " + scene().string() + quick_flags() + " --quiet --out " +
                                             (dir_ / "quiet").string());
  ASSERT_EQ(code, 0) << out;
  std::vector<std::string> lines = absl::StrSplit(out, '\n', absl::SkipEmpty());
  ASSERT_EQ(lines.size(), 1u) << out;
  EXPECT_TRUE(contains(lines[0], "test PSNR")) << out;
  EXPECT_TRUE(contains(lines[0], "outputs in " + (dir_ / "quiet").string())) << out;
  // Warnings stay.
  const auto [budget_code, budget_out] =
      test::run_command(kGaps + " train " + scene().string() + quick_flags() + " --quiet --max-gaussians 100 --out " +
                        (dir_ / "budget").string());
  ASSERT_EQ(budget_code, 0) << budget_out;
  EXPECT_TRUE(contains(budget_out, "warning: the 300 initial Gaussians already fill the budget")) << budget_out;
}

// 7: types in words, ranges without the types' limits, integers as integers.
TEST_F(Frictions, OptionsSpeakUserWords) {
  const auto [code, out] = test::run_command(kGaps + " options");
  ASSERT_EQ(code, 0) << out;
  for (const char* cpp : {"std::", "uint64_t", "int64_t", "| int |", "| double |", "| bool |"})
    EXPECT_FALSE(contains(out, cpp)) << cpp;
  EXPECT_FALSE(std::regex_search(out, std::regex("\\[[^\\]|]*e\\+"))) << "a range in exponent notation:\n" << out;
  EXPECT_TRUE(contains(out, "| training | `iterations` | integer | `10000` | [1, 1000000] |")) << out;
  EXPECT_TRUE(contains(out, "| training | `seed` | integer | `0` | >= 0 |")) << out;
  EXPECT_TRUE(contains(out, "| training | `lambda_dssim` | number | `0.2` | [0, 1] |")) << out;
  EXPECT_TRUE(contains(out, "| training | `device` | text | `\"cpu\"` |  |")) << out;
  EXPECT_TRUE(contains(out, "| training | `max_gaussians` | integer | `0` | [0, 67108864] |")) << out;
}

// 8: one line pointing at the table in each command's help; the table in one place.
TEST_F(Frictions, CommandHelpPointsToTheExitCodeTableInsteadOfRepeatingIt) {
  for (const char* command : {"train", "submit", "fetch", "render", "options"}) {
    const auto [code, help] = test::run_command(kGaps + " " + command + " --help");
    EXPECT_EQ(code, 0) << help;
    EXPECT_TRUE(contains(help, "gaps help exit-codes")) << command;
    EXPECT_FALSE(contains(help, "  130  ")) << command << " repeats the table:\n" << help;
  }
  const auto [code, table] = test::run_command(kGaps + " help exit-codes");
  EXPECT_EQ(code, 0) << table;
  EXPECT_TRUE(contains(table, "  130  gaps train stopped by SIGINT")) << table;
  EXPECT_TRUE(contains(test::run_command(kGaps + " --help").second, "  130  ")) << "the overview keeps it";
  EXPECT_TRUE(contains(test::run_command(kGaps + " help fetch").second, "usage: gaps fetch JOB"));
  expect_failure(test::run_command(kGaps + " help nothing"), 2, "gaps help takes one topic");
}

// 9: every TLS mistake gets its own message, against trainers in each set-up.
TEST_F(Frictions, EachTlsMistakeIsNamed) {
  if (std::system("openssl version > /dev/null 2>&1") != 0) GTEST_SKIP() << "openssl not found: no test certificates";
  const std::string d = dir_.string() + "/";
  ASSERT_TRUE(test::make_test_certificates(dir_));
  const std::vector<std::string> tls = {"--tls-cert", d + "localhost.pem", "--tls-key", d + "localhost.key"};
  std::string plain_at, tls_at, mutual_at;
  auto plain = trainer("plain", {}, &plain_at);
  auto with_tls = trainer("tls", tls, &tls_at);
  std::vector<std::string> mutual_flags = tls;
  mutual_flags.insert(mutual_flags.end(), {"--tls-client-ca", d + "ca.pem"});
  auto mutual = trainer("mutual", mutual_flags, &mutual_at);
  const auto list = [&](const std::string& at, const std::string& flags) {
    return test::run_command(kGaps + " list --trainer " + at + " " + flags);
  };
  const std::string ca = "--tls-ca " + d + "ca.pem --tls-server-name localhost";
  EXPECT_EQ(list(tls_at, ca).first, 0);
  expect_failure(list(tls_at, "--tls-ca " + d + "rogue.pem --tls-server-name localhost"), 5,
                 "the trainer's certificate is not trusted by --tls-ca " + d + "rogue.pem");
  expect_failure(list(tls_at, "--tls-ca " + d + "ca.pem"), 5,
                 "the trainer's certificate is for localhost, not for 127.0.0.1: give --tls-server-name localhost");
  expect_failure(list(tls_at, ""), 5, "the trainer requires TLS and this client spoke plaintext: give --tls-ca");
  expect_failure(list(plain_at, ca), 5, "the trainer speaks plaintext, not TLS: leave out --tls-ca");
  expect_failure(list(mutual_at, ca), 5, "the trainer requires a client certificate (mutual TLS)");
  expect_failure(list(mutual_at, ca + " --tls-client-cert " + d + "rogue.pem --tls-client-key " + d + "rogue.key"), 5,
                 "the trainer refused the client certificate " + d + "rogue.pem");
  EXPECT_EQ(list(mutual_at, ca + " --tls-client-cert " + d + "client.pem --tls-client-key " + d + "client.key").first,
            0);
}

}  // namespace
}  // namespace gaps

// The client-server system with real processes on loopback: gaps-worker and gaps-trainer are started on
// free ports, scenes are submitted through the client library, events watched to the end and artifacts
// fetched and checked. Faults: corrupt uploads, wrong tokens, a worker killed mid-job, a trainer killed
// mid-job and restarted, cancellation.
#include <fcntl.h>
#include <signal.h>
#include <spawn.h>
#include <sys/wait.h>
#include <unistd.h>

#include <chrono>
#include <cmath>
#include <fstream>
#include <regex>
#include <thread>

#include <ATen/ATen.h>
#include <gtest/gtest.h>
#include <nlohmann/json.hpp>

#include "absl/strings/match.h"
#include "absl/strings/str_join.h"
#include "client/remote_client.h"
#include "common/image_io.h"
#include "common/io_util.h"
#include "common/ply.h"
#include "gs_trainer/model/gaussians.h"
#include "gs_trainer/scene/bounds.h"
#include "gs_trainer/scene/camera_path.h"
#include "gs_trainer/scene/cameras_json.h"
#include "gs_trainer/scene/colmap.h"
#include "gs_trainer/scene/scene.h"
#include "gs_trainer/synthetic.h"
#include "rpc/codec.h"
#include "rpc/config_codec.h"
#include "tests/option_values.h"
#include "tests/process_util.h"
#include "tests/synthetic_scene_util.h"
#include "tests/test_util.h"

extern char** environ;

namespace gaps {
namespace {

using test::read_json;

namespace fs = std::filesystem;
using test::Process;
using test::run_command;

struct Services : test::TempDirTest {
  void SetUp() override {
    test::TempDirTest::SetUp();
    std::ofstream(dir_ / "token") << "e2e-secret-token\n";
    std::ofstream(dir_ / "wrong_token") << "not-the-token\n";
  }

  std::unique_ptr<Process> start_worker() {
    auto p = std::make_unique<Process>(std::vector<std::string>{GAPS_WORKER_BIN, "--listen", "127.0.0.1:0", "--backend",
                                                                "reproject", "--token_file", (dir_ / "token").string()},
                                       dir_ / "worker.log");
    worker_port = p->wait_for_port();
    return p;
  }

  std::unique_ptr<Process> start_trainer(const std::vector<std::string>& extra = {}) {
    std::vector<std::string> argv = {GAPS_TRAINER_BIN,
                                     "--listen",
                                     "127.0.0.1:0",
                                     "--data_dir",
                                     (dir_ / "data").string(),
                                     "--device",
                                     "cpu",
                                     "--token_file",
                                     (dir_ / "token").string(),
                                     "--worker_token_file",
                                     (dir_ / "token").string(),
                                     "--workers",
                                     "127.0.0.1:" + std::to_string(worker_port),
                                     "--worker_rounds",
                                     "2"};
    argv.insert(argv.end(), extra.begin(), extra.end());
    auto p = std::make_unique<Process>(argv, dir_ / ("trainer" + std::to_string(trainer_starts++) + ".log"));
    trainer_port = p->wait_for_port();
    return p;
  }

  client::TrainerClient connect(const std::string& token = "e2e-secret-token", const std::string& ca = "") {
    auto c = client::TrainerClient::connect("127.0.0.1:" + std::to_string(trainer_port),
                                            {token, ca, ca.empty() ? "" : "localhost"});
    EXPECT_TRUE(c.ok());
    return std::move(*c);
  }

  // A synthetic scene of 9 images in dir_/<folder>, by default small for quick jobs.
  client::PreparedScene synthetic_scene(int width = 64, int height = 48, const std::string& folder = "synthetic") {
    auto scene = test::prepared_synthetic_scene(dir_ / folder, width, height);
    EXPECT_TRUE(scene.ok()) << scene.status();
    return *scene;
  }

  static v1::JobSpec spec(const std::string& variant, int iterations, nlohmann::json gaps = nlohmann::json::object()) {
    v1::JobSpec s;
    s.set_name("test");
    s.mutable_config()->set_views(3);
    s.mutable_config()->set_init("random");
    s.mutable_config()->set_random_points(1500);
    s.mutable_config()->set_variant(variant);
    s.mutable_config()->mutable_training()->set_iterations(iterations);
    EXPECT_TRUE(rpc::set_fields(gaps, s.mutable_config()->mutable_gaps()).ok());
    return s;
  }

  // The flags that reach the started trainer.
  std::string trainer_flags() const {
    return " --trainer 127.0.0.1:" + std::to_string(trainer_port) + " --token-file " + (dir_ / "token").string();
  }

  // `gaps submit SCENE FLAGS --watch` to the started trainer, then `gaps fetch` of its job into `fetched`;
  // *out: what submit printed.
  void submit_watch_fetch(const fs::path& scene, const std::string& flags, const fs::path& fetched, std::string* out) {
    const std::string gaps_cli = GAPS_CLI_BIN;
    int code = 0;
    std::tie(code, *out) = run_command(gaps_cli + " submit " + scene.string() + flags + " --watch" + trainer_flags());
    ASSERT_EQ(code, 0) << *out;
    std::smatch m;
    ASSERT_TRUE(std::regex_search(*out, m, std::regex("job-[0-9a-f]+"))) << *out;
    const auto [fetch_code, fetch_out] =
        run_command(gaps_cli + " fetch " + std::string(m[0]) + " -o " + fetched.string() + trainer_flags());
    ASSERT_EQ(fetch_code, 0) << fetch_out;
  }

  int worker_port = -1;
  int trainer_port = -1;
  int trainer_starts = 0;
};

struct Seen {
  int progress = 0, phases_started = 0, phases_done = 0, phases_skipped = 0;
  std::vector<std::string> logs;
};

void count(const v1::JobEvent& e, Seen& seen) {
  seen.progress += e.has_progress();
  seen.phases_started += e.has_phase_started();
  if (e.has_phase_finished()) (e.phase_finished().skipped() ? seen.phases_skipped : seen.phases_done) += 1;
  if (e.has_log()) seen.logs.push_back(e.log());
}

bool have_openssl() { return std::system("openssl version > /dev/null 2>&1") == 0; }

TEST_F(Services, FernThreeViewsThroughTlsWithTokenEndToEnd) {
  const fs::path fern = fs::path(GAPS_DATA_DIR) / "llff" / "fern";
  if (!fs::exists(fern)) GTEST_SKIP() << "benchmark data not found at " << fern;
  if (!have_openssl()) GTEST_SKIP() << "openssl not found: no test certificate can be made";
  const std::string make_cert =
      "openssl req -x509 -newkey rsa:2048 -nodes -days 1 -subj /CN=localhost "
      "-addext subjectAltName=DNS:localhost -keyout " +
      (dir_ / "key.pem").string() + " -out " + (dir_ / "cert.pem").string() + " > /dev/null 2>&1";
  ASSERT_EQ(std::system(make_cert.c_str()), 0);
  auto worker = start_worker();
  ASSERT_GT(worker_port, 0) << worker->log_text();
  auto trainer = start_trainer({"--tls_cert", (dir_ / "cert.pem").string(), "--tls_key", (dir_ / "key.pem").string()});
  ASSERT_GT(trainer_port, 0) << trainer->log_text();
  const std::string ca = (dir_ / "cert.pem").string();

  // Plaintext and wrong tokens are refused.
  EXPECT_FALSE(connect("e2e-secret-token", "").list().ok());
  const auto refused = connect("not-the-token", ca).list();
  EXPECT_EQ(refused.status().code(), absl::StatusCode::kUnauthenticated) << refused.status();

  client::TrainerClient client = connect("e2e-secret-token", ca);
  auto scene = client::prepare_scene(fern, 8);
  ASSERT_TRUE(scene.ok()) << scene.status();
  v1::JobSpec s = spec("full", 300, {{"warmup_iterations", 100}, {"phase_interval", 100}, {"n_active", 2}});
  s.set_name("fern");
  s.mutable_config()->set_random_points(2500);
  auto job = client.submit(s, *scene);
  ASSERT_TRUE(job.ok()) << job.status();
  Seen seen;
  auto final_status = client.watch(*job, [&](const v1::JobEvent& e) { count(e, seen); });
  ASSERT_TRUE(final_status.ok()) << final_status.status() << "\n" << trainer->log_text();
  ASSERT_EQ(final_status->state(), v1::SUCCEEDED) << final_status->error();
  EXPECT_EQ(seen.phases_started, 2);  // iterations 100 and 200
  EXPECT_EQ(seen.phases_done, 2);
  EXPECT_EQ(seen.phases_skipped, 0);
  EXPECT_GE(seen.progress, 30);
  EXPECT_EQ(final_status->iteration(), 300);

  auto files = client.fetch(*job, dir_ / "fetched");
  ASSERT_TRUE(files.ok()) << files.status();
  auto model = load_gaussians_ply(dir_ / "fetched" / "point_cloud.ply");
  ASSERT_TRUE(model.ok()) << model.status();
  EXPECT_EQ(model->size(), final_status->num_gaussians());
  const auto metrics = read_json(dir_ / "fetched" / "metrics.json");
  EXPECT_GT(metrics["psnr"].get<double>(), 12.0);
  EXPECT_NEAR(metrics["psnr"].get<double>(), final_status->psnr(), 1e-9);
  EXPECT_EQ(metrics["variant"], "full");
  EXPECT_EQ(metrics["iterations"], 300);
  EXPECT_EQ(metrics["generator"].get<std::string>().rfind("remote reproject", 0), 0u) << metrics["generator"];
  EXPECT_EQ(read_json(dir_ / "fetched" / "phases.json").size(), 2u);
  EXPECT_TRUE(fs::exists(dir_ / "fetched" / "renders"));
}

TEST_F(Services, CorruptUploadsAndWrongTokensAreRefusedAndOtherJobsUntouched) {
  auto worker = start_worker();
  ASSERT_GT(worker_port, 0) << worker->log_text();
  auto trainer = start_trainer();
  ASSERT_GT(trainer_port, 0) << trainer->log_text();
  client::TrainerClient client = connect();
  const client::PreparedScene good = synthetic_scene();
  auto kept = client.submit(spec("vanilla", 60), good);
  ASSERT_TRUE(kept.ok()) << kept.status();

  const auto expect_invalid = [&](const client::PreparedScene& scene, const std::string& needle) {
    auto r = client.submit(spec("vanilla", 60), scene);
    ASSERT_FALSE(r.ok());
    EXPECT_EQ(r.status().code(), absl::StatusCode::kInvalidArgument) << r.status();
    EXPECT_NE(r.status().message().find(needle), std::string_view::npos) << r.status();
  };
  client::PreparedScene bad = good;
  bad.images[2] = "\x89PNG garbage";
  expect_invalid(bad, "image 2");
  bad = good;
  bad.cameras.pop_back();
  expect_invalid(bad, "camera count mismatch");
  bad = good;
  bad.cameras[5].set_translation(0, std::nan(""));
  expect_invalid(bad, "camera 5");

  const auto refused = connect("not-the-token").submit(spec("vanilla", 60), good);
  EXPECT_EQ(refused.status().code(), absl::StatusCode::kUnauthenticated) << refused.status();

  auto jobs = client.list();
  ASSERT_TRUE(jobs.ok());
  ASSERT_EQ(jobs->size(), 1u);  // none of the refused uploads became a job
  auto final_status = client.watch(*kept, [](const v1::JobEvent&) {});
  ASSERT_TRUE(final_status.ok()) << final_status.status();
  EXPECT_EQ(final_status->state(), v1::SUCCEEDED) << final_status->error();
}

TEST_F(Services, KilledWorkerSkipsTheRemainingPhasesAndTheJobFinishes) {
  auto worker = start_worker();
  ASSERT_GT(worker_port, 0) << worker->log_text();
  auto trainer = start_trainer();
  ASSERT_GT(trainer_port, 0) << trainer->log_text();
  client::TrainerClient client = connect();
  auto job = client.submit(spec("full", 120, {{"warmup_iterations", 30}, {"phase_interval", 40}, {"n_active", 2}}),
                           synthetic_scene());
  ASSERT_TRUE(job.ok()) << job.status();
  Seen seen;
  auto final_status = client.watch(*job, [&](const v1::JobEvent& e) {
    count(e, seen);
    if (e.has_phase_finished() && e.phase_finished().phase() == 0) worker->kill(SIGKILL);
  });
  ASSERT_TRUE(final_status.ok()) << final_status.status();
  EXPECT_EQ(final_status->state(), v1::SUCCEEDED) << final_status->error();
  EXPECT_EQ(seen.phases_started, 3);  // iterations 30, 70, 110
  EXPECT_EQ(seen.phases_done, 1);
  EXPECT_EQ(seen.phases_skipped, 2);
  const bool warned = std::any_of(seen.logs.begin(), seen.logs.end(), [](const std::string& l) {
    return l.find("skipped, training continues") != std::string::npos;
  });
  EXPECT_TRUE(warned);
  // Succeeded, but not a full run of the method: the status, list and metrics.json say so.
  EXPECT_TRUE(final_status->degraded());
  EXPECT_EQ(final_status->phases(), 3);
  EXPECT_EQ(final_status->phases_skipped(), 2);
  auto listed = client.list();
  ASSERT_TRUE(listed.ok());
  ASSERT_EQ(listed->size(), 1u);
  EXPECT_TRUE((*listed)[0].degraded());
  ASSERT_TRUE(client.fetch(*job, dir_ / "fetched").ok());
  const auto metrics = read_json(dir_ / "fetched" / "metrics.json");
  EXPECT_EQ(metrics["degraded"], true);
  EXPECT_EQ(metrics["phases_skipped"], 2);
  const auto report = read_file_bytes(dir_ / "fetched" / "report.html");
  ASSERT_TRUE(report.ok()) << report.status();
  EXPECT_TRUE(absl::StrContains(*report, "DEGRADED: 2 of 3 diffusion phases were skipped")) << *report;
  EXPECT_TRUE(absl::StrContains(*report, "<tr><th>diffusion phases</th><td>3 run, 2 skipped</td></tr>"));
}

TEST_F(Services, KilledTrainerResumesItsJobFromTheCheckpointAfterRestart) {
  auto worker = start_worker();
  ASSERT_GT(worker_port, 0);
  auto trainer = start_trainer();
  ASSERT_GT(trainer_port, 0) << trainer->log_text();
  std::string job_id;
  int checkpoint = -1;
  {
    client::TrainerClient client = connect();
    auto job = client.submit(spec("full", 150, {{"warmup_iterations", 30}, {"phase_interval", 60}, {"n_active", 2}}),
                             synthetic_scene());
    ASSERT_TRUE(job.ok()) << job.status();
    job_id = *job;
    // Kill the trainer once a checkpoint exists and training went past it; the watch then ends early.
    auto interrupted = client.watch(job_id, [&](const v1::JobEvent& e) {
      if (e.has_checkpoint_written()) checkpoint = e.checkpoint_written();
      if (e.has_progress() && checkpoint >= 0 && e.progress().iteration() >= 50) trainer->kill(SIGKILL);
    });
    EXPECT_FALSE(interrupted.ok());
  }
  ASSERT_EQ(checkpoint, 29);  // the start of phase 0, before iteration 30
  trainer = start_trainer();
  ASSERT_GT(trainer_port, 0) << trainer->log_text();
  client::TrainerClient client = connect();
  Seen seen;
  int first_progress_after_resume = -1;
  bool resumed = false;
  auto final_status = client.watch(job_id, [&](const v1::JobEvent& e) {
    count(e, seen);
    if (e.has_log() && e.log() == "resumed from the checkpoint at iteration 29") resumed = true;
    if (resumed && e.has_progress() && first_progress_after_resume < 0)
      first_progress_after_resume = e.progress().iteration();
  });
  ASSERT_TRUE(final_status.ok()) << final_status.status() << "\n" << trainer->log_text();
  EXPECT_EQ(final_status->state(), v1::SUCCEEDED) << final_status->error();
  EXPECT_EQ(final_status->resumes(), 1);
  EXPECT_EQ(final_status->iteration(), 150);
  EXPECT_TRUE(resumed);
  EXPECT_EQ(first_progress_after_resume, 30);  // not from iteration 0
}

// A job whose trainer keeps dying while it runs (a poison job) is FAILED at the second crash instead of
// taking every restart down with it; the trainer then serves on.
TEST_F(Services, AJobThatKeepsKillingItsTrainerIsQuarantined) {
  auto worker = start_worker();
  auto trainer = start_trainer();
  ASSERT_GT(trainer_port, 0) << trainer->log_text();
  std::string job_id;
  for (int crash = 0; crash < 2; ++crash) {
    client::TrainerClient client = connect();
    if (job_id.empty()) {
      auto job = client.submit(spec("vanilla", 100000), synthetic_scene());
      ASSERT_TRUE(job.ok()) << job.status();
      job_id = *job;
    }
    // Progress of this trainer's run, not the history the watch replays first.
    const double since = std::chrono::duration<double>(std::chrono::system_clock::now().time_since_epoch()).count();
    (void)client.watch(job_id, [&](const v1::JobEvent& e) {
      if (e.has_progress() && e.time() > since) trainer->kill(SIGKILL);
    });
    trainer = start_trainer();
    ASSERT_GT(trainer_port, 0) << trainer->log_text();
  }
  client::TrainerClient client = connect();
  auto status = client.watch(job_id, [](const v1::JobEvent&) {});
  ASSERT_TRUE(status.ok()) << status.status();
  EXPECT_EQ(status->state(), v1::FAILED);
  EXPECT_EQ(status->crashes(), 2);
  EXPECT_NE(status->error().find("the trainer died 2 times while running this job"), std::string::npos)
      << status->error();
  EXPECT_TRUE(client.list().ok());
}

// The trainer's own token (what clients present to it) is not what it presents to workers: without
// --worker_token_file it sends none, so a worker requiring one refuses and the phases are skipped.
TEST_F(Services, TheTrainersOwnTokenIsNeverSentToWorkers) {
  auto worker = start_worker();
  ASSERT_GT(worker_port, 0) << worker->log_text();
  Process trainer({GAPS_TRAINER_BIN, "--listen", "127.0.0.1:0", "--data_dir", (dir_ / "data").string(), "--device",
                   "cpu", "--token_file", (dir_ / "token").string(), "--workers",
                   "127.0.0.1:" + std::to_string(worker_port), "--worker_rounds", "1"},
                  dir_ / "trainer_no_worker_token.log");
  trainer_port = trainer.wait_for_port();
  ASSERT_GT(trainer_port, 0) << trainer.log_text();
  client::TrainerClient client = connect();
  auto job = client.submit(spec("full", 60, {{"warmup_iterations", 20}, {"phase_interval", 40}, {"n_active", 2}}),
                           synthetic_scene());
  ASSERT_TRUE(job.ok()) << job.status();
  Seen seen;
  auto status = client.watch(*job, [&](const v1::JobEvent& e) { count(e, seen); });
  ASSERT_TRUE(status.ok()) << status.status();
  EXPECT_EQ(seen.phases_done, 0);
  EXPECT_EQ(seen.phases_skipped, 1);  // the one phase, at iteration 20
  EXPECT_TRUE(status->degraded());
}

// One data folder, one trainer; one port, one server.
TEST_F(Services, ASecondTrainerOnTheSameDataFolderOrPortIsRefused) {
  auto worker = start_worker();
  auto first = start_trainer();
  ASSERT_GT(trainer_port, 0) << first->log_text();
  const int first_port = trainer_port;
  auto second = start_trainer();
  EXPECT_EQ(trainer_port, -1);
  EXPECT_NE(second->log_text().find("is in use by another gaps-trainer"), std::string::npos) << second->log_text();
  Process same_port({GAPS_TRAINER_BIN, "--listen", "127.0.0.1:" + std::to_string(first_port), "--data_dir",
                     (dir_ / "other_data").string(), "--device", "cpu"},
                    dir_ / "same_port.log");
  EXPECT_EQ(same_port.wait_for_port(std::chrono::seconds(30)), -1) << same_port.log_text();
  EXPECT_FALSE(same_port.running());
  // Said in those words, before gRPC could log its own page of internal error text.
  EXPECT_NE(same_port.log_text().find("port " + std::to_string(first_port) + " is in use by another program"),
            std::string::npos)
      << same_port.log_text();
  EXPECT_EQ(same_port.log_text().find("chttp2_server"), std::string::npos) << same_port.log_text();
}

TEST_F(Services, SigtermStopsTheTrainerGracefullyAndTheJobRunsAgainOnRestart) {
  auto worker = start_worker();
  auto trainer = start_trainer();
  ASSERT_GT(trainer_port, 0) << trainer->log_text();
  std::string job_id;
  int exit_code = -2;
  {
    client::TrainerClient client = connect();
    auto job = client.submit(spec("vanilla", 120), synthetic_scene());
    ASSERT_TRUE(job.ok()) << job.status();
    job_id = *job;
    auto interrupted = client.watch(job_id, [&](const v1::JobEvent& e) {
      if (e.has_progress() && e.progress().iteration() >= 20 && exit_code == -2)
        exit_code = trainer->stop(SIGTERM, std::chrono::seconds(30));
    });
    EXPECT_FALSE(interrupted.ok());
  }
  EXPECT_EQ(exit_code, 0) << trainer->log_text();
  EXPECT_NE(trainer->log_text().find("running jobs resume"), std::string::npos) << trainer->log_text();
  trainer = start_trainer();
  ASSERT_GT(trainer_port, 0) << trainer->log_text();
  // The stop wrote a checkpoint (a vanilla job has no phase checkpoints), and the job went on from it.
  int resumed_at = -1, first_progress_after_resume = -1;
  auto final_status = connect().watch(job_id, [&](const v1::JobEvent& e) {
    if (e.has_log() && e.log().rfind("resumed from the checkpoint at iteration ", 0) == 0)
      resumed_at = std::stoi(e.log().substr(e.log().rfind(' ') + 1));
    if (resumed_at >= 0 && e.has_progress() && first_progress_after_resume < 0)
      first_progress_after_resume = e.progress().iteration();
  });
  ASSERT_TRUE(final_status.ok()) << final_status.status();
  EXPECT_EQ(final_status->state(), v1::SUCCEEDED) << final_status->error();
  EXPECT_EQ(final_status->resumes(), 1);
  EXPECT_GE(resumed_at, 20);
  EXPECT_GT(first_progress_after_resume, resumed_at);
}

TEST_F(Services, CancelStopsARunningJob) {
  auto worker = start_worker();
  auto trainer = start_trainer();
  ASSERT_GT(trainer_port, 0) << trainer->log_text();
  client::TrainerClient client = connect();
  auto job = client.submit(spec("vanilla", 1000000), synthetic_scene());
  ASSERT_TRUE(job.ok()) << job.status();
  bool cancel_sent = false;
  auto final_status = client.watch(*job, [&](const v1::JobEvent& e) {
    if (e.has_progress() && !cancel_sent) {
      cancel_sent = true;
      EXPECT_TRUE(client.cancel(*job).ok());
    }
  });
  ASSERT_TRUE(final_status.ok()) << final_status.status();
  EXPECT_EQ(final_status->state(), v1::CANCELLED);
  EXPECT_LT(final_status->iteration(), 1000000);
  // Artifacts of a cancelled job: the model so far, no metrics.
  auto files = client.fetch(*job, dir_ / "fetched");
  ASSERT_TRUE(files.ok()) << files.status();
  EXPECT_TRUE(fs::exists(dir_ / "fetched" / "point_cloud.ply"));
  EXPECT_FALSE(fs::exists(dir_ / "fetched" / "metrics.json"));
}

// A job cancelled while still initialising stops there (between the stages, or at the next PatchMatch
// sweep), not once its initialisation is done: this one's PatchMatch alone would take minutes on a CPU.
TEST_F(Services, CancelStopsAJobStillInitialising) {
  auto trainer = start_trainer();
  ASSERT_GT(trainer_port, 0) << trainer->log_text();
  client::TrainerClient client = connect();
  const client::PreparedScene scene = synthetic_scene(640, 480, "large");
  v1::JobSpec job_spec = spec("vanilla", 100);
  job_spec.mutable_config()->set_init("mvs");
  ASSERT_TRUE(rpc::set_fields({{"patchmatch_iterations", 60}, {"patchmatch_max_image_side", 640}},
                              job_spec.mutable_config()->mutable_init_settings())
                  .ok());
  auto job = client.submit(job_spec, scene);
  ASSERT_TRUE(job.ok()) << job.status();
  // Cancelled once PatchMatch says it has begun: the stages are visible as job events, and the job shows as
  // INITIALISING meanwhile.
  bool cancel_sent = false;
  std::string listed;
  auto final_status = client.watch(*job, [&](const v1::JobEvent& e) {
    if (!cancel_sent && e.has_log() && absl::StartsWith(e.log(), "init: PatchMatch: 0/")) {
      cancel_sent = true;
      listed = run_command(std::string(GAPS_CLI_BIN) + " list" + trainer_flags()).second;
      EXPECT_TRUE(client.cancel(*job).ok());
    }
  });
  ASSERT_TRUE(final_status.ok()) << final_status.status();
  EXPECT_TRUE(cancel_sent) << "no PatchMatch progress event";
  EXPECT_NE(listed.find(*job + "  INITIALISING"), std::string::npos) << listed;
  // The trainer's own log follows the job: its arrival, start and end.
  for (const std::string state : {"QUEUED", "RUNNING", "CANCELLED: cancelled: "})
    EXPECT_NE(trainer->log_text().find("gaps-trainer: job " + *job + ": " + state), std::string::npos)
        << state << "\n"
        << trainer->log_text();
  EXPECT_EQ(final_status->state(), v1::CANCELLED) << final_status->error();
  EXPECT_TRUE(std::regex_match(final_status->error(),
                               std::regex("cancelled: (PatchMatch stopped at view [0-9]+|initialisation stopped "
                                          "(before|after) the sparse points)")))
      << final_status->error();
  EXPECT_EQ(final_status->iteration(), 0);
}

// Runs a command line, returning its exit code and output.
TEST_F(Services, CommandLineSubmitWatchListFetch) {
  auto worker = start_worker();
  auto trainer = start_trainer();
  ASSERT_GT(trainer_port, 0) << trainer->log_text();
  synthetic_scene();
  const std::string common =
      " --trainer 127.0.0.1:" + std::to_string(trainer_port) + " --token-file " + (dir_ / "token").string();
  const std::string gaps = GAPS_CLI_BIN;
  auto [code, out] =
      run_command(gaps + " submit " + (dir_ / "synthetic").string() +
                  " --views 3 --resolution 1 --iterations 40 --init random --random-points 500" + common);
  ASSERT_EQ(code, 0) << out;
  std::smatch m;
  ASSERT_TRUE(std::regex_search(out, m, std::regex("job-[0-9a-f]+"))) << out;
  const std::string job = m[0];
  std::tie(code, out) = run_command(gaps + " watch " + job + " --quiet" + common);
  EXPECT_EQ(code, 0) << out;
  EXPECT_NE(out.find("SUCCEEDED"), std::string::npos) << out;
  std::tie(code, out) = run_command(gaps + " list" + common);
  EXPECT_EQ(code, 0) << out;
  EXPECT_NE(out.find(job), std::string::npos) << out;
  // The trainer measures LPIPS with the set-up's weights, as gaps train does.
  EXPECT_NE(out.find("LPIPS 0."), std::string::npos) << out;
  std::tie(code, out) = run_command(gaps + " fetch " + job + " -o " + (dir_ / "cli_out").string() + common);
  EXPECT_EQ(code, 0) << out;
  EXPECT_TRUE(fs::exists(dir_ / "cli_out" / "metrics.json")) << out;
  const nlohmann::json fetched = read_json(dir_ / "cli_out" / "metrics.json");
  EXPECT_TRUE(fetched["lpips"].is_number()) << fetched["lpips"];
  for (const nlohmann::json& view : fetched["per_view"]) EXPECT_TRUE(view["lpips"].is_number()) << view;
  EXPECT_TRUE(fs::exists(dir_ / "cli_out" / "point_cloud.ply")) << out;
  // RenderView at a test pose reproduces the job's own render of that view (renders/ of the artifacts).
  client::TrainerClient client = connect();
  const client::PreparedScene scene = synthetic_scene();
  auto rendered = client.render(job, scene.cameras[0]);
  ASSERT_TRUE(rendered.ok()) << rendered.status();
  auto saved = read_image(dir_ / "cli_out" / "renders" / scene.cameras[0].name());
  ASSERT_TRUE(saved.ok()) << saved.status();
  EXPECT_LE((*rendered - *saved).abs().max().item<float>(), 1.0f / 255 + 1e-6);
  EXPECT_GT(rendered->std().item<float>(), 0.01f);  // not a blank image
  v1::Camera bad = scene.cameras[0];
  bad.set_fx(-1);
  EXPECT_EQ(client.render(job, bad).status().code(), absl::StatusCode::kInvalidArgument);
  // A camera whose render would not fit the trainer's memory is refused before anything is allocated.
  for (const int side : {16384, 65536}) {
    v1::Camera huge = scene.cameras[0];
    huge.set_width(side);
    huge.set_height(side);
    const absl::Status refused = client.render(job, huge).status();
    EXPECT_EQ(refused.code(), absl::StatusCode::kInvalidArgument) << refused;
    EXPECT_NE(refused.message().find("over the limit of 16777216 pixels per render"), std::string::npos) << refused;
  }
  std::tie(code, out) = run_command(gaps + " list --trainer 127.0.0.1:" + std::to_string(trainer_port) +
                                    " --token-file " + (dir_ / "wrong_token").string());
  EXPECT_NE(code, 0);
  EXPECT_NE(out.find("invalid bearer token"), std::string::npos) << out;
}

// `gaps render --job` draws a path through a finished fern job on its trainer (RenderView per frame, cameras from
// GetJobCameras): the test path gives the job's own test renders, and an orbit's frames circle the point they
// look at at the training cameras' mean distance. Submitted as a job's points, the job's PLY is a full model.
TEST_F(Services, RenderJobDrawsPathsWithTheJobsCamerasAndAJobFromItsPlyContinuesIt) {
  const fs::path fern = fs::path(GAPS_DATA_DIR) / "llff" / "fern";
  if (!fs::exists(fern)) GTEST_SKIP() << "benchmark data not found at " << fern;
  auto worker = start_worker();
  auto trainer = start_trainer();
  ASSERT_GT(trainer_port, 0) << trainer->log_text();
  client::TrainerClient client = connect();
  auto scene = client::prepare_scene(fern, 8);
  ASSERT_TRUE(scene.ok()) << scene.status();
  auto job = client.submit(spec("vanilla", 10), *scene);
  ASSERT_TRUE(job.ok()) << job.status();
  EXPECT_EQ(client.job_cameras(*job).status().code(), absl::StatusCode::kFailedPrecondition);  // not finished yet
  auto status = client.watch(*job, [](const v1::JobEvent&) {});
  ASSERT_TRUE(status.ok() && status->state() == v1::SUCCEEDED) << trainer->log_text();
  ASSERT_TRUE(client.fetch(*job, dir_ / "fetched").ok());

  auto listed = client.job_cameras(*job);
  ASSERT_TRUE(listed.ok()) << listed.status();
  ASSERT_EQ(listed->train_size(), 3);
  ASSERT_EQ(listed->test_size(), 3);  // fern's 20 images: every 8th is a test view
  EXPECT_EQ(listed->test(1).name(), scene->cameras[8].name());
  EXPECT_GT(listed->near(), 0);
  EXPECT_GT(listed->far(), listed->near());
  std::vector<Camera> train;
  for (const v1::Camera& c : listed->train()) train.push_back(*rpc::decode_camera(c, "camera"));

  const std::string common = " --job " + *job + " --quiet --trainer 127.0.0.1:" + std::to_string(trainer_port) +
                             " --token-file " + (dir_ / "token").string();
  auto [code, out] =
      run_command(std::string(GAPS_CLI_BIN) + " render --path test --out " + (dir_ / "test_path").string() + common);
  ASSERT_EQ(code, 0) << out;
  for (int k = 0; k < 3; ++k) {
    auto frame = read_image(dir_ / "test_path" / ("0000" + std::to_string(k) + ".png"));
    auto saved = read_image(dir_ / "fetched" / "renders" / listed->test(k).name());
    ASSERT_TRUE(frame.ok() && saved.ok()) << listed->test(k).name();
    EXPECT_LE((*frame - *saved).abs().max().item<float>(), 1.0f / 255 + 1e-6) << listed->test(k).name();
  }

  std::tie(code, out) = run_command(std::string(GAPS_CLI_BIN) + " render --path orbit --frames 4 --out " +
                                    (dir_ / "orbit").string() + common);
  ASSERT_EQ(code, 0) << out;
  auto frames = read_cameras_json(dir_ / "orbit" / "cameras.json");
  ASSERT_TRUE(frames.ok()) << frames.status();
  ASSERT_EQ(frames->size(), 4u);
  std::vector<Camera> orbit;
  for (const auto& r : *frames) orbit.push_back(r.camera);
  const auto centre = optical_axes_target(orbit);
  ASSERT_TRUE(centre.has_value());
  double distance = 0;
  for (const Camera& c : train) distance += (c.center() - *centre).norm() / train.size();
  for (const Camera& c : orbit) EXPECT_NEAR((c.center() - *centre).norm(), distance, 1e-6 * distance);
  for (int k = 0; k < 4; ++k) EXPECT_TRUE(fs::exists(dir_ / "orbit" / ("0000" + std::to_string(k) + ".png")));
  // A job submitted with the finished model's PLY as its points continues that model.
  client::PreparedScene continued = *scene;
  auto ply = read_file_bytes(dir_ / "fetched" / "point_cloud.ply", "model");
  ASSERT_TRUE(ply.ok()) << ply.status();
  continued.points_ply = *ply;
  v1::JobSpec from_model = spec("vanilla", 1);
  from_model.mutable_config()->set_init("points");
  auto job2 = client.submit(from_model, continued);
  ASSERT_TRUE(job2.ok()) << job2.status();
  Seen seen;
  auto status2 = client.watch(*job2, [&](const v1::JobEvent& e) { count(e, seen); });
  ASSERT_TRUE(status2.ok() && status2->state() == v1::SUCCEEDED) << trainer->log_text();
  EXPECT_EQ(status2->num_gaussians(), status->num_gaussians());
  EXPECT_TRUE(std::any_of(seen.logs.begin(), seen.logs.end(), [](const std::string& l) {
    return absl::StrContains(l, "is a full 3DGS model");
  })) << absl::StrJoin(seen.logs, "\n");

  std::tie(code, out) = run_command(std::string(GAPS_CLI_BIN) + " render --out " + (dir_ / "none").string() +
                                    " --job job-unknown --trainer 127.0.0.1:" + std::to_string(trainer_port) +
                                    " --token-file " + (dir_ / "token").string());
  EXPECT_NE(code, 0);
  EXPECT_NE(out.find("job-unknown"), std::string::npos) << out;
}

// One pair of config files with every option away from its default: `gaps train` in process and `gaps submit`
// to a trainer service must run with, and record in metrics.json, the same configuration.
TEST_F(Services, TrainAndSubmitRecordTheSameConfigurationForEveryOption) {
  const fs::path fern = fs::path(GAPS_DATA_DIR) / "llff" / "fern";
  if (!fs::exists(fern)) GTEST_SKIP() << "benchmark data not found at " << fern;
  // Short, CPU, and with phases: the overrides keep those while every value still differs from its default (a
  // budget density given, not another automatic one, which the run resolves).
  const nlohmann::json training = test::non_default_options(train_config_options(), {{"iterations", 60},
                                                                                     {"device", "cpu"},
                                                                                     {"opacity_reset_interval", 5000},
                                                                                     {"max_gaussians", 30000},
                                                                                     {"gaussians_per_variation", 2.5},
                                                                                     {"seed", 3}});
  const nlohmann::json gaps = test::non_default_options(
      gaps_config_options(), {{"warmup_iterations", 20}, {"phase_interval", 20}, {"n_active", 2}});
  std::ofstream(dir_ / "training.json") << training.dump(2);
  std::ofstream(dir_ / "gaps.json") << gaps.dump(2);
  const std::string gaps_cli = GAPS_CLI_BIN;
  // The file's seed 3 is overridden by the flag, and the run says so.
  const std::string run_flags =
      " --views 3 --resolution 8 --variant full --init random --random-points 1500 --quiet"
      " --seed 4 --config " +
      (dir_ / "training.json").string() + " --gaps-config " + (dir_ / "gaps.json").string();
  auto [code, out] =
      run_command(gaps_cli + " train --scene " + fern.string() + " --out " + (dir_ / "local").string() + run_flags);
  ASSERT_EQ(code, 0) << out;
  EXPECT_NE(out.find("seed = 4 from the command line, over 3 in"), std::string::npos) << out;

  auto worker = start_worker();
  auto trainer = start_trainer();
  ASSERT_GT(trainer_port, 0) << trainer->log_text();
  ASSERT_NO_FATAL_FAILURE(submit_watch_fetch(fern, run_flags, dir_ / "remote", &out)) << trainer->log_text();
  EXPECT_NE(out.find("seed = 4 from the command line, over 3 in"), std::string::npos) << out;

  nlohmann::json local = read_json(dir_ / "local" / "metrics.json");
  nlohmann::json remote = read_json(dir_ / "remote" / "metrics.json");
  nlohmann::json expected_training = training;
  expected_training["seed"] = 4;
  EXPECT_EQ(local["config"], expected_training);
  EXPECT_EQ(local["gaps"], gaps);
  // What differs by construction: where the scene and generator live, and the service receives images already
  // downscaled by the client (resolution 1).
  for (const char* key : {"scene", "generator", "resolution", "init_resolution"}) {
    local.erase(key);
    remote.erase(key);
  }
  for (const char* key : {"config", "gaps", "iterations", "views", "device", "seed", "init", "init_method",
                          "init_points", "random_points", "variant"})
    EXPECT_EQ(local[key], remote[key]) << key;
  // Random points are drawn between the scene's depth bounds (LLFF's poses_bounds.npy): the upload must carry
  // them, or the job starts from points elsewhere and ends far below the local run (10.6 against 18.1 dB once).
  EXPECT_EQ(out.find("depth bounds: not given"), std::string::npos) << out;
  EXPECT_NEAR(local["psnr"].get<double>(), remote["psnr"].get<double>(), 0.5);
}

// --init scene: the points a COLMAP scene ships reach the job as its initial points (the upload itself carries
// only images and cameras), so gaps submit starts from the cloud gaps train starts from.
TEST_F(Services, TrainAndSubmitStartFromTheScenesOwnPoints) {
  const fs::path transforms = dir_ / "transforms_scene";
  ASSERT_TRUE(write_synthetic_scene(transforms, {16, 64, 48, 0}).ok());
  const absl::StatusOr<Scene> loaded = load_scene(transforms);
  ASSERT_TRUE(loaded.ok()) << loaded.status();
  at::manual_seed(0);
  const PointCloud points{at::rand({300, 3}) * 2 - 1, at::rand({300, 3})};
  const fs::path colmap = dir_ / "colmap_scene";
  ASSERT_TRUE(write_colmap_text(colmap / "sparse" / "0", colmap_from_cameras(loaded->cameras, points)).ok());
  fs::copy(transforms / "images", colmap / "images", fs::copy_options::recursive);
  const std::string run_flags =
      " --views 3 --resolution 1 --variant vanilla --iterations 20 --device cpu --eval-every 0 --init scene --quiet";
  auto [code, out] = run_command(std::string(GAPS_CLI_BIN) + " train --scene " + colmap.string() + " --out " +
                                 (dir_ / "local").string() + run_flags);
  ASSERT_EQ(code, 0) << out;
  auto trainer = start_trainer();
  ASSERT_GT(trainer_port, 0) << trainer->log_text();
  ASSERT_NO_FATAL_FAILURE(submit_watch_fetch(colmap, run_flags, dir_ / "remote", &out)) << trainer->log_text();
  const nlohmann::json local = read_json(dir_ / "local" / "metrics.json");
  const nlohmann::json remote = read_json(dir_ / "remote" / "metrics.json");
  EXPECT_EQ(local["init_points"], 300) << local;
  EXPECT_EQ(remote["init_points"], 300) << remote;
  EXPECT_NEAR(local["psnr"].get<double>(), remote["psnr"].get<double>(), 0.5);
}

// Every other --init (random and auto have their own tests above and below, scene just above): the job starts
// from as many points as gaps train with the same flags: fern 3 views at -r 32 (resized on load, so the upload's
// 8-bit PNGs must hold what the local run reads), PatchMatch made cheap for the CPU.
TEST_F(Services, TrainAndSubmitStartFromTheSameCloudForEveryInit) {
  const fs::path fern = fs::path(GAPS_DATA_DIR) / "llff" / "fern";
  if (!fs::exists(fern)) GTEST_SKIP() << "benchmark data not found at " << fern;
  at::manual_seed(0);
  const fs::path ply = dir_ / "points.ply";
  ASSERT_TRUE(write_point_cloud_ply({at::rand({200, 3}) * 2 - 1, at::rand({200, 3})}, ply).ok());
  // The trainer shares gaps train's cache (--init-cache): what the local run computed, the job reuses, which
  // it can only when the same cameras, images and settings reached it (the cache key covers all three).
  auto trainer = start_trainer({"--init-cache", (dir_ / "cache").string()});
  ASSERT_GT(trainer_port, 0) << trainer->log_text();
  for (const std::string init : {"mvs", "sweep", "sparse", "ply"}) {
    SCOPED_TRACE(init);
    const std::string run_flags =
        " --views 3 --resolution 32 --variant vanilla --iterations 20 --device cpu --eval-every 0 --quiet"
        " --patchmatch-iterations 3 --patchmatch-geometric-consistency=false --init " +
        init + (init == "ply" ? " --init-ply " + ply.string() : "");
    auto [code, out] =
        run_command(std::string(GAPS_CLI_BIN) + " train --scene " + fern.string() + " --out " +
                    (dir_ / ("local_" + init)).string() + " --init-cache " + (dir_ / "cache").string() + run_flags);
    ASSERT_EQ(code, 0) << out;
    ASSERT_NO_FATAL_FAILURE(submit_watch_fetch(fern, run_flags, dir_ / ("remote_" + init), &out))
        << trainer->log_text();
    const nlohmann::json local = read_json(dir_ / ("local_" + init) / "metrics.json");
    const nlohmann::json remote = read_json(dir_ / ("remote_" + init) / "metrics.json");
    EXPECT_GT(local["init_points"].get<int64_t>(), 0) << local;
    EXPECT_EQ(local["init_points"], remote["init_points"]) << "local " << local << "\nremote " << remote;
    EXPECT_EQ(local["init_method"], remote["init_method"]);
    if (init != "ply") EXPECT_EQ(remote["init_from_cache"], true) << init;
  }
}

// "auto" on a forward-facing capture reads the training views at twice their size: `gaps submit` uploads them
// (FileChunk::LARGER_IMAGE), so the service starts from the very cloud `gaps train` starts from. PatchMatch is
// made cheap for the CPU; fern 3 views at -r 16, PatchMatch on the -r 8 views.
TEST_F(Services, TrainAndSubmitStartAutoFromTheSameLargerViews) {
  const fs::path fern = fs::path(GAPS_DATA_DIR) / "llff" / "fern";
  if (!fs::exists(fern)) GTEST_SKIP() << "benchmark data not found at " << fern;
  const std::string gaps_cli = GAPS_CLI_BIN;
  const std::string run_flags =
      " --views 3 --resolution 16 --variant vanilla --iterations 20 --device cpu --eval-every 0"
      " --patchmatch-iterations 3 --patchmatch-geometric-consistency=false";
  auto [code, out] = run_command(gaps_cli + " train --scene " + fern.string() + " --out " + (dir_ / "local").string() +
                                 " --init-cache " + (dir_ / "cache").string() + run_flags);
  ASSERT_EQ(code, 0) << out;
  const std::string larger =
      "init: auto: the views face one way, so PatchMatch reads them at twice the training "
      "size (504 pixels on the longest side)";
  EXPECT_NE(out.find(larger), std::string::npos) << out;
  const std::string local_out = out;
  std::smatch local_points, remote_points;
  ASSERT_TRUE(std::regex_search(local_out, local_points, std::regex("initial points: ([0-9]+)"))) << out;

  auto trainer = start_trainer();
  ASSERT_GT(trainer_port, 0) << trainer->log_text();
  ASSERT_NO_FATAL_FAILURE(submit_watch_fetch(fern, run_flags, dir_ / "remote", &out)) << trainer->log_text();
  EXPECT_NE(out.find(larger), std::string::npos) << out;
  ASSERT_TRUE(std::regex_search(out, remote_points, std::regex("initial points: ([0-9]+)"))) << out;
  // On the CPU gaps train names the flag that keeps the training views; the job, which gaps submit made and
  // which cannot take that flag, does not.
  EXPECT_NE(local_out.find("(--init-resolution 16 keeps the training views)"), std::string::npos) << local_out;
  EXPECT_EQ(out.find("--init-resolution"), std::string::npos) << out;
  // Its stages are said as they go, by gaps train and through the job's events alike.
  for (const std::string& said : {local_out, out})
    for (const std::string stage : {"init: sparse points (SIFT, matching, triangulation): done in ",
                                    "init: PatchMatch: 0/", "init: fusion of the depth maps: done in "})
      EXPECT_NE(said.find(stage), std::string::npos) << stage << "\n" << said;
  EXPECT_EQ(local_points[1], remote_points[1]) << "the same views and settings make the same cloud\n"
                                               << local_out << "\n"
                                               << out;
  const nlohmann::json local = read_json(dir_ / "local" / "metrics.json");
  const nlohmann::json remote = read_json(dir_ / "remote" / "metrics.json");
  EXPECT_EQ(local["init_method"], "mvs");
  EXPECT_EQ(remote["init_method"], "mvs");
  EXPECT_EQ(local["init_options"], remote["init_options"]);
  EXPECT_EQ(local["init_options"]["patchmatch_max_image_side"], 504) << local["init_options"];
  EXPECT_EQ(local["init_options"]["sparse_max_image_side"], 252) << local["init_options"];
  EXPECT_EQ(local["init_resolution"], 8);
  EXPECT_EQ(remote["init_resolution"], 0.5) << "twice the size of the upload";
}

}  // namespace
}  // namespace gaps

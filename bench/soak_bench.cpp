// Soak and load of the services as users run them: a gaps-trainer and a gaps-worker (separate processes on
// loopback) take N jobs of a real scene while, for a bounded time, the worker is killed (SIGKILL) and
// restarted every few tens of seconds and the trainer is stopped (SIGKILL and SIGTERM in turn) and
// restarted. Then the chaos stops and every job is waited for. Reports jobs completed, failed and degraded,
// phases run and skipped, resumes and crashes counted by the trainer, restarts done, submit retries, the
// processes' resident memory over time, and whether anything was lost: every submitted job must reach a
// final state, and every succeeded one must have its model, metrics and report.
//   soak_bench [--jobs 6] [--chaos_seconds 600] [--worker_kill_every 45] [--trainer_kill_every 100]
//              [--scene DIR] [--resolution 8] [--iterations 300] [--work_dir DIR]
#include <signal.h>

#include <chrono>
#include <fstream>
#include <iostream>
#include <map>
#include <memory>
#include <set>

#include <nlohmann/json.hpp>
#include "absl/flags/flag.h"
#include "absl/flags/parse.h"
#include "absl/strings/str_cat.h"
#include "client/remote_client.h"
#include "common/io_util.h"
#include "rpc/config_codec.h"
#include "tests/process_util.h"

ABSL_FLAG(int, jobs, 6, "jobs submitted (half at the start, the rest during the chaos)");
ABSL_FLAG(int, chaos_seconds, 600, "how long processes are killed and restarted");
ABSL_FLAG(int, worker_kill_every, 45, "seconds between worker kills");
ABSL_FLAG(int, trainer_kill_every, 100, "seconds between trainer stops (SIGKILL and SIGTERM in turn)");
ABSL_FLAG(int, drain_seconds, 1800, "longest wait for the jobs after the chaos");
ABSL_FLAG(std::string, scene, GAPS_DATA_DIR "/llff/fern", "scene folder");
ABSL_FLAG(int, resolution, 8, "downscale factor");
ABSL_FLAG(int, iterations, 300, "training iterations per job");
ABSL_FLAG(std::string, device, "cpu", "device of both services (cpu, cuda, cuda:N)");
ABSL_FLAG(double, checkpoint_seconds, 120, "the trainer's --checkpoint-seconds");
ABSL_FLAG(std::string, work_dir, "/tmp/gaps_soak_bench", "folder for logs, the trainer's data and fetched results");
ABSL_FLAG(std::string, trainer_bin, GAPS_TRAINER_BIN, "the gaps-trainer executable");
ABSL_FLAG(std::string, worker_bin, GAPS_WORKER_BIN, "the gaps-worker executable");

namespace {

namespace fs = std::filesystem;
using Clock = std::chrono::steady_clock;
using gaps::test::Process;

double rss_mib(const Process& p) {
  if (p.pid() <= 0) return 0;
  std::ifstream status("/proc/" + std::to_string(p.pid()) + "/status");
  std::string line;
  while (std::getline(status, line))
    if (line.rfind("VmRSS:", 0) == 0) return std::stod(line.substr(6)) / 1024.0;
  return 0;
}

class Services {
 public:
  explicit Services(const fs::path& dir) : dir_(dir) {}

  bool start_worker() {
    const std::string listen = absl::StrCat("127.0.0.1:", worker_port_ > 0 ? worker_port_ : 0);
    worker_ = std::make_unique<Process>(
        std::vector<std::string>{absl::GetFlag(FLAGS_worker_bin), "--listen", listen, "--backend", "reproject",
                                 "--device", absl::GetFlag(FLAGS_device)},
        dir_ / absl::StrCat("worker_", worker_starts_++, ".log"));
    worker_port_ = worker_->wait_for_port();
    return worker_port_ > 0;
  }

  bool start_trainer() {
    const std::string listen = absl::StrCat("127.0.0.1:", trainer_port_ > 0 ? trainer_port_ : 0);
    trainer_ = std::make_unique<Process>(
        std::vector<std::string>{absl::GetFlag(FLAGS_trainer_bin), "--listen", listen, "--data_dir",
                                 (dir_ / "data").string(), "--device", absl::GetFlag(FLAGS_device), "--workers",
                                 absl::StrCat("127.0.0.1:", worker_port_),
                                 // Every kill here is the benchmark's, not a poison job: no quarantine.
                                 "--max_crashes", "1000000", "--worker_timeout_s", "60", "--checkpoint_seconds",
                                 absl::StrCat(absl::GetFlag(FLAGS_checkpoint_seconds))},
        dir_ / absl::StrCat("trainer_", trainer_starts_++, ".log"));
    trainer_port_ = trainer_->wait_for_port();
    return trainer_port_ > 0;
  }

  void kill_worker() { worker_->kill(SIGKILL); }
  // SIGKILL on odd stops, SIGTERM (a clean stop that checkpoints) on even ones.
  void stop_trainer() {
    if (++trainer_stops_ % 2 == 1)
      trainer_->kill(SIGKILL);
    else if (trainer_->stop(SIGTERM, std::chrono::seconds(120)) < 0)
      trainer_->kill(SIGKILL);
  }
  std::string trainer_address() const { return absl::StrCat("127.0.0.1:", trainer_port_); }
  double trainer_rss() const { return trainer_ ? rss_mib(*trainer_) : 0; }
  double worker_rss() const { return worker_ ? rss_mib(*worker_) : 0; }
  int worker_starts() const { return worker_starts_; }
  int trainer_starts() const { return trainer_starts_; }
  int trainer_stops() const { return trainer_stops_; }

 private:
  fs::path dir_;
  std::unique_ptr<Process> worker_, trainer_;
  int worker_port_ = -1, trainer_port_ = -1;
  int worker_starts_ = 0, trainer_starts_ = 0, trainer_stops_ = 0;
};

gaps::v1::JobSpec job_spec(int index) {
  gaps::v1::JobSpec s;
  s.set_name(absl::StrCat("soak-", index));
  s.mutable_config()->set_views(3);
  s.mutable_config()->set_variant("full");
  s.mutable_config()->mutable_training()->set_iterations(absl::GetFlag(FLAGS_iterations));
  s.mutable_config()->mutable_training()->set_seed(index);
  const int iterations = absl::GetFlag(FLAGS_iterations);
  const nlohmann::json gaps = {
      {"warmup_iterations", iterations / 4}, {"phase_interval", iterations / 4}, {"n_active", 4}};
  if (auto st = gaps::rpc::set_fields(gaps, s.mutable_config()->mutable_gaps()); !st.ok()) {
    std::cerr << "soak_bench: " << st << "\n";
    std::exit(1);
  }
  return s;
}

bool terminal(gaps::v1::JobState s) {
  return s == gaps::v1::SUCCEEDED || s == gaps::v1::FAILED || s == gaps::v1::CANCELLED;
}

}  // namespace

int main(int argc, char** argv) {
  absl::ParseCommandLine(argc, argv);
  const fs::path dir = absl::GetFlag(FLAGS_work_dir);
  gaps::remove_tree(dir);
  fs::create_directories(dir);
  const int jobs = absl::GetFlag(FLAGS_jobs);
  auto scene = gaps::client::prepare_scene(absl::GetFlag(FLAGS_scene), absl::GetFlag(FLAGS_resolution));
  if (!scene.ok()) {
    std::cerr << "soak_bench: " << scene.status() << "\n";
    return 1;
  }
  Services services(dir);
  if (!services.start_worker() || !services.start_trainer()) {
    std::cerr << "soak_bench: the services did not start; logs in " << dir << "\n";
    return 1;
  }

  std::vector<std::string> submitted;
  int submit_retries = 0;
  // A client whose trainer is down retries (the trainer is restarted within seconds).
  const auto submit = [&](int index) {
    for (;;) {
      auto client = gaps::client::TrainerClient::connect(services.trainer_address(), {});
      if (client.ok()) {
        auto job = client->submit(job_spec(index), *scene);
        if (job.ok()) return submitted.push_back(*job);
      }
      ++submit_retries;
      std::this_thread::sleep_for(std::chrono::seconds(1));
    }
  };
  for (int i = 0; i < (jobs + 1) / 2; ++i) submit(i);

  nlohmann::json memory = nlohmann::json::array();
  const auto start = Clock::now();
  const auto seconds = [&] { return std::chrono::duration<double>(Clock::now() - start).count(); };
  const int chaos = absl::GetFlag(FLAGS_chaos_seconds);
  const int worker_every = absl::GetFlag(FLAGS_worker_kill_every);
  const int trainer_every = absl::GetFlag(FLAGS_trainer_kill_every);
  double next_worker_kill = worker_every, next_trainer_stop = trainer_every, next_sample = 0;
  int next_job = (jobs + 1) / 2;
  const double submit_spacing = static_cast<double>(chaos) / std::max(1, jobs - next_job + 1);
  double next_submit = submit_spacing;
  bool drained = false;
  while (!drained) {
    const double t = seconds();
    if (t >= next_sample) {
      memory.push_back(
          {{"t", std::round(t)}, {"trainer_mib", services.trainer_rss()}, {"worker_mib", services.worker_rss()}});
      next_sample += 5;
    }
    if (t < chaos) {
      if (t >= next_worker_kill) {
        services.kill_worker();
        std::this_thread::sleep_for(std::chrono::seconds(2));
        if (!services.start_worker()) return (std::cerr << "soak_bench: the worker did not restart\n", 1);
        next_worker_kill += worker_every;
      }
      if (t >= next_trainer_stop) {
        services.stop_trainer();
        if (!services.start_trainer()) return (std::cerr << "soak_bench: the trainer did not restart\n", 1);
        next_trainer_stop += trainer_every;
      }
      if (next_job < jobs && t >= next_submit) {
        submit(next_job++);
        next_submit += submit_spacing;
      }
    } else {
      while (next_job < jobs) submit(next_job++);
      auto client = gaps::client::TrainerClient::connect(services.trainer_address(), {});
      auto listed = client.ok() ? client->list() : absl::StatusOr<std::vector<gaps::v1::JobStatus>>(client.status());
      if (listed.ok())
        drained = std::all_of(listed->begin(), listed->end(), [](const auto& j) { return terminal(j.state()); });
      if (t > chaos + absl::GetFlag(FLAGS_drain_seconds)) break;
    }
    std::this_thread::sleep_for(std::chrono::milliseconds(500));
  }

  auto client = gaps::client::TrainerClient::connect(services.trainer_address(), {});
  auto listed = client->list();
  if (!listed.ok()) return (std::cerr << "soak_bench: " << listed.status() << "\n", 1);
  std::map<std::string, gaps::v1::JobStatus> by_id;
  for (const auto& j : *listed) by_id[j.job_id()] = j;
  // lost: a submitted job the trainer does not know; unfinished: known but not ended by the deadline.
  int succeeded = 0, failed = 0, degraded = 0, phases = 0, skipped = 0, resumes = 0, crashes = 0, lost = 0;
  int unfinished = 0;
  int incomplete_artifacts = 0;
  nlohmann::json per_job = nlohmann::json::array();
  for (const auto& id : submitted) {
    if (!by_id.count(id)) {
      ++lost;
      continue;
    }
    if (!terminal(by_id[id].state())) {
      ++unfinished;
      per_job.push_back({{"job", id},
                         {"state", gaps::v1::JobState_Name(by_id[id].state())},
                         {"iteration", by_id[id].iteration()},
                         {"resumes", by_id[id].resumes()}});
      continue;
    }
    const auto& j = by_id[id];
    succeeded += j.state() == gaps::v1::SUCCEEDED;
    failed += j.state() == gaps::v1::FAILED;
    degraded += j.degraded();
    phases += j.phases();
    skipped += j.phases_skipped();
    resumes += j.resumes();
    crashes += j.crashes();
    const fs::path out = dir / "fetched" / id;
    bool complete = false;
    if (j.state() == gaps::v1::SUCCEEDED && client->fetch(id, out).ok())
      complete =
          fs::exists(out / "point_cloud.ply") && fs::exists(out / "metrics.json") && fs::exists(out / "report.html");
    incomplete_artifacts += j.state() == gaps::v1::SUCCEEDED && !complete;
    per_job.push_back({{"job", id},
                       {"state", gaps::v1::JobState_Name(j.state())},
                       {"error", j.error()},
                       {"phases", j.phases()},
                       {"phases_skipped", j.phases_skipped()},
                       {"resumes", j.resumes()},
                       {"crashes", j.crashes()},
                       {"artifacts_complete", complete}});
  }
  double trainer_peak = 0, worker_peak = 0;
  for (const auto& m : memory) {
    trainer_peak = std::max(trainer_peak, m["trainer_mib"].get<double>());
    worker_peak = std::max(worker_peak, m["worker_mib"].get<double>());
  }
  const nlohmann::json summary = {{"bench", "soak"},
                                  {"jobs", jobs},
                                  {"scene", absl::GetFlag(FLAGS_scene)},
                                  {"iterations", absl::GetFlag(FLAGS_iterations)},
                                  {"device", absl::GetFlag(FLAGS_device)},
                                  {"checkpoint_seconds", absl::GetFlag(FLAGS_checkpoint_seconds)},
                                  {"chaos_seconds", chaos},
                                  {"wall_seconds", std::round(seconds())},
                                  {"succeeded", succeeded},
                                  {"failed", failed},
                                  {"degraded", degraded},
                                  {"phases", phases},
                                  {"phases_skipped", skipped},
                                  {"resumes_counted", resumes},
                                  {"crashes_counted", crashes},
                                  {"trainer_stops", services.trainer_stops()},
                                  {"worker_kills", services.worker_starts() - 1},
                                  {"submit_retries", submit_retries},
                                  {"lost", lost},
                                  {"succeeded_without_artifacts", incomplete_artifacts},
                                  {"trainer_peak_rss_mib", trainer_peak},
                                  {"worker_peak_rss_mib", worker_peak},
                                  {"per_job", per_job},
                                  {"memory", memory}};
  std::cout << summary.dump() << "\n";
  return lost == 0 && unfinished == 0 && incomplete_artifacts == 0 ? 0 : 1;
}

// Throughput of small CPU jobs with 1 and with N trainer replicas sharing a PostgreSQL job store and one data
// folder (the scale-out deployment), side by side in one run on one machine: a private PostgreSQL server
// (tests/postgres_server.h), the real gaps-trainer binaries, vanilla jobs of a synthetic scene submitted all
// at once. Reports per setting the makespan, jobs per minute, and the queue latency of each job (submit to
// start, which includes waiting for a free replica; and the start delay of the first jobs, which is the
// claim latency: how long a job that a free replica could run waits before it starts).
//   replicas_bench [--jobs 9] [--replicas 1,3] [--iterations 300] [--work_dir DIR]
#include <signal.h>

#include <algorithm>
#include <iostream>
#include <thread>

#include <nlohmann/json.hpp>
#include "absl/flags/flag.h"
#include "absl/flags/parse.h"
#include "absl/strings/numbers.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_split.h"
#include "client/remote_client.h"
#include "common/io_util.h"
#include "gs_trainer/synthetic.h"
#include "tests/postgres_server.h"
#include "tests/process_util.h"

ABSL_FLAG(int, jobs, 9, "jobs per setting");
ABSL_FLAG(std::string, replicas, "1,3", "replica counts to compare");
ABSL_FLAG(int, iterations, 300, "training iterations per job");
ABSL_FLAG(std::string, work_dir, "/tmp/gaps_replicas_bench", "scratch folder");

namespace {

namespace fs = std::filesystem;
using Clock = std::chrono::steady_clock;

gaps::v1::JobSpec job_spec(int index) {
  gaps::v1::JobSpec s;
  s.set_name(absl::StrCat("bench-", index));
  s.mutable_config()->set_views(3);
  s.mutable_config()->set_init("random");
  s.mutable_config()->set_random_points(2000);
  s.mutable_config()->set_variant("vanilla");
  s.mutable_config()->mutable_training()->set_iterations(absl::GetFlag(FLAGS_iterations));
  s.mutable_config()->mutable_training()->set_seed(index);
  return s;
}

absl::StatusOr<nlohmann::json> run_setting(int replicas, const fs::path& dir,
                                           const gaps::client::PreparedScene& scene) {
  auto postgres = gaps::test::PostgresServer::start(dir / "pg");
  if (!postgres.ok()) return postgres.status();
  if (auto st = (*postgres)->create_database("gaps"); !st.ok()) return st;
  std::vector<std::unique_ptr<gaps::test::Process>> trainers;
  std::vector<int> ports;
  for (int r = 0; r < replicas; ++r) {
    trainers.push_back(std::make_unique<gaps::test::Process>(
        std::vector<std::string>{GAPS_TRAINER_BIN, "--listen", "127.0.0.1:0", "--data_dir", (dir / "data").string(),
                                 "--job_store", (*postgres)->uri("gaps"), "--replica_id", absl::StrCat("replica-", r),
                                 "--device", "cpu"},
        dir / absl::StrCat("trainer", r, ".log")));
    ports.push_back(trainers.back()->wait_for_port());
    if (ports.back() <= 0) return absl::InternalError("a trainer did not start: " + trainers.back()->log_text());
  }
  auto client = gaps::client::TrainerClient::connect(absl::StrCat("127.0.0.1:", ports[0]), {});
  if (!client.ok()) return client.status();
  const auto start = Clock::now();
  const int jobs = absl::GetFlag(FLAGS_jobs);
  for (int j = 0; j < jobs; ++j) {
    auto job = client->submit(job_spec(j), scene);
    if (!job.ok()) return job.status();
  }
  std::vector<gaps::v1::JobStatus> done;
  while (true) {
    auto listed = client->list();
    if (!listed.ok()) return listed.status();
    done.clear();
    for (const auto& j : *listed)
      if (j.state() == gaps::v1::SUCCEEDED || j.state() == gaps::v1::FAILED) done.push_back(j);
    if (static_cast<int>(done.size()) == jobs) break;
    std::this_thread::sleep_for(std::chrono::milliseconds(200));
  }
  const double makespan = std::chrono::duration<double>(Clock::now() - start).count();
  std::vector<double> waits;
  int failed = 0;
  for (const auto& j : done) {
    waits.push_back(j.started_at() - j.submitted_at());
    failed += j.state() != gaps::v1::SUCCEEDED;
  }
  std::sort(waits.begin(), waits.end());
  // The first `replicas` jobs find a free replica: their wait is the claim latency alone.
  double claim = 0;
  for (int k = 0; k < replicas && k < jobs; ++k) claim = std::max(claim, waits[k]);
  return nlohmann::json{{"replicas", replicas},
                        {"jobs", jobs},
                        {"failed", failed},
                        {"makespan_s", makespan},
                        {"jobs_per_minute", jobs / makespan * 60},
                        {"queue_wait_median_s", waits[waits.size() / 2]},
                        {"queue_wait_max_s", waits.back()},
                        {"claim_latency_max_s", claim}};
}

}  // namespace

int main(int argc, char** argv) {
  absl::ParseCommandLine(argc, argv);
  const fs::path dir = absl::GetFlag(FLAGS_work_dir);
  gaps::remove_tree(dir);
  gaps::SyntheticSceneOptions s;
  s.images = 9;
  s.width = 64;
  s.height = 48;
  if (auto st = gaps::write_synthetic_scene(dir / "scene", s); !st.ok()) return (std::cerr << st << "\n", 1);
  auto scene = gaps::client::prepare_scene(dir / "scene", 1);
  if (!scene.ok()) return (std::cerr << scene.status() << "\n", 1);
  for (absl::string_view count : absl::StrSplit(absl::GetFlag(FLAGS_replicas), ',')) {
    int replicas = 0;
    if (!absl::SimpleAtoi(count, &replicas) || replicas < 1) return (std::cerr << "bad --replicas\n", 2);
    auto result = run_setting(replicas, dir / absl::StrCat("r", replicas), *scene);
    if (!result.ok()) return (std::cerr << "replicas_bench: " << result.status() << "\n", 1);
    std::cout << result->dump() << std::endl;
  }
  return 0;
}

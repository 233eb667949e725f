// Scale-out on loopback: a real PostgreSQL server, three gaps-trainer replicas sharing it and one data
// folder, two gaps-worker processes. Six small CPU jobs go in through different replicas; the replica
// running one of them is killed (SIGKILL) mid-job. Every job must succeed exactly once (one closing event,
// the killed one resumed once by another replica), every event stream must be whole and gapless from any
// replica, and every job's artifacts must be fetchable through any live replica.
#include <signal.h>

#include <algorithm>
#include <map>
#include <set>
#include <thread>

#include <gtest/gtest.h>
#include <nlohmann/json.hpp>
#include "absl/strings/match.h"
#include "client/remote_client.h"
#include "common/io_util.h"
#include "rpc/config_codec.h"
#include "tests/postgres_server.h"
#include "tests/process_util.h"
#include "tests/synthetic_scene_util.h"
#include "tests/test_util.h"

namespace gaps {
namespace {

namespace fs = std::filesystem;
using test::Process;

constexpr int kReplicas = 3, kWorkers = 2, kJobs = 6;

struct ScaleOut : test::TempDirTest {
  void SetUp() override {
    test::TempDirTest::SetUp();
    auto pg = test::PostgresServer::start(dir_ / "pg");
    ASSERT_TRUE(pg.ok()) << pg.status();
    postgres = std::move(*pg);
    ASSERT_TRUE(postgres->create_database("gaps").ok());
    auto prepared = test::prepared_synthetic_scene(dir_ / "synthetic", 48, 36);
    ASSERT_TRUE(prepared.ok()) << prepared.status();
    scene = *prepared;
  }

  void start_worker(int i) {
    workers[i] = std::make_unique<Process>(
        std::vector<std::string>{GAPS_WORKER_BIN, "--listen", "127.0.0.1:0", "--backend", "reproject"},
        dir_ / ("worker" + std::to_string(i) + ".log"));
    worker_ports[i] = workers[i]->wait_for_port();
  }

  void start_trainer(int i) {
    std::string worker_list;
    for (int w = 0; w < kWorkers; ++w)
      worker_list += (w ? ",127.0.0.1:" : "127.0.0.1:") + std::to_string(worker_ports[w]);
    trainers[i] = std::make_unique<Process>(
        std::vector<std::string>{GAPS_TRAINER_BIN, "--listen", "127.0.0.1:0", "--data_dir", (dir_ / "data").string(),
                                 "--job_store", postgres->uri("gaps"), "--replica_id", name(i), "--lease_seconds", "3",
                                 "--device", "cpu", "--workers", worker_list},
        dir_ / (name(i) + ".log"));
    trainer_ports[i] = trainers[i]->wait_for_port();
  }

  static std::string name(int i) { return "replica-" + std::to_string(i); }

  client::TrainerClient through(int i) {
    auto c = client::TrainerClient::connect("127.0.0.1:" + std::to_string(trainer_ports[i]), {});
    EXPECT_TRUE(c.ok());
    return std::move(*c);
  }

  static v1::JobSpec spec(int index) {
    v1::JobSpec s;
    s.set_name("scale-out " + std::to_string(index));
    s.mutable_config()->set_views(3);
    s.mutable_config()->set_init("random");
    s.mutable_config()->set_random_points(800);
    s.mutable_config()->set_variant("full");
    s.mutable_config()->mutable_training()->set_iterations(150);
    s.mutable_config()->mutable_training()->set_seed(index);
    EXPECT_TRUE(rpc::set_fields({{"warmup_iterations", 40}, {"phase_interval", 50}, {"n_active", 2}},
                                s.mutable_config()->mutable_gaps())
                    .ok());
    return s;
  }

  std::unique_ptr<test::PostgresServer> postgres;
  client::PreparedScene scene;
  std::unique_ptr<Process> workers[kWorkers], trainers[kReplicas];
  int worker_ports[kWorkers] = {}, trainer_ports[kReplicas] = {};
};

bool terminal(v1::JobState s) { return s == v1::SUCCEEDED || s == v1::FAILED || s == v1::CANCELLED; }

TEST_F(ScaleOut, SixJobsThroughThreeReplicasSurviveAKilledReplicaAndEndOnce) {
  for (int w = 0; w < kWorkers; ++w) {
    start_worker(w);
    ASSERT_GT(worker_ports[w], 0) << workers[w]->log_text();
  }
  for (int r = 0; r < kReplicas; ++r) {
    start_trainer(r);
    ASSERT_GT(trainer_ports[r], 0) << trainers[r]->log_text();
  }
  std::vector<std::string> jobs;
  for (int j = 0; j < kJobs; ++j) {
    auto job = through(j % kReplicas).submit(spec(j), scene);
    ASSERT_TRUE(job.ok()) << job.status();
    jobs.push_back(*job);
  }

  // Kill the replica that runs the first job found past its first phase.
  int killed = -1;
  std::string victim;
  const auto deadline = std::chrono::steady_clock::now() + std::chrono::minutes(5);
  while (killed < 0 && std::chrono::steady_clock::now() < deadline) {
    auto listed = through(0).list();
    ASSERT_TRUE(listed.ok()) << listed.status();
    for (const auto& j : *listed)
      if (j.state() == v1::RUNNING && j.iteration() >= 60 && !j.runner().empty()) {
        killed = std::stoi(j.runner().substr(j.runner().rfind('-') + 1));
        victim = j.job_id();
        break;
      }
    if (killed < 0) std::this_thread::sleep_for(std::chrono::milliseconds(200));
  }
  ASSERT_GE(killed, 0) << "no job got past iteration 60";
  trainers[killed]->kill(SIGKILL);
  const int alive[2] = {(killed + 1) % kReplicas, (killed + 2) % kReplicas};

  std::map<std::string, v1::JobStatus> final;
  while (final.size() < jobs.size() && std::chrono::steady_clock::now() < deadline + std::chrono::minutes(10)) {
    auto listed = through(alive[0]).list();
    ASSERT_TRUE(listed.ok()) << listed.status();
    for (const auto& j : *listed)
      if (terminal(j.state())) final[j.job_id()] = j;
    std::this_thread::sleep_for(std::chrono::milliseconds(500));
  }
  ASSERT_EQ(final.size(), jobs.size()) << "jobs still open; logs in " << dir_;

  for (size_t k = 0; k < jobs.size(); ++k) {
    const v1::JobStatus& j = final[jobs[k]];
    EXPECT_EQ(j.state(), v1::SUCCEEDED) << j.job_id() << ": " << j.error();
    if (j.job_id() == victim) {
      EXPECT_EQ(j.resumes(), 1) << "the killed replica's job is taken over once";
      EXPECT_EQ(j.crashes(), 1);
      EXPECT_NE(j.runner(), name(killed));
    } else {
      EXPECT_EQ(j.resumes(), 0) << j.job_id();
    }
    // The whole history, through either live replica: gapless, opened once, closed once and last.
    auto client = through(alive[k % 2]);
    std::vector<v1::JobEvent> events;
    auto watched = client.watch(jobs[k], [&](const v1::JobEvent& e) { events.push_back(e); });
    ASSERT_TRUE(watched.ok()) << watched.status();
    ASSERT_FALSE(events.empty());
    int closings = 0, queued = 0;
    for (size_t s = 0; s < events.size(); ++s) {
      EXPECT_EQ(events[s].sequence(), static_cast<int64_t>(s)) << jobs[k];
      closings += events[s].has_finished() || events[s].has_failed() || events[s].has_cancelled();
      queued += events[s].has_state_changed() && events[s].state_changed() == v1::QUEUED;
    }
    EXPECT_EQ(closings, 1) << jobs[k] << " ended more than once";
    const bool taken_over = std::any_of(events.begin(), events.end(), [](const v1::JobEvent& e) {
      return e.has_log() && absl::StrContains(e.log(), "takes the job over");
    });
    EXPECT_EQ(taken_over, jobs[k] == victim) << jobs[k];
    EXPECT_TRUE(events.back().has_finished()) << jobs[k];
    EXPECT_EQ(queued, 1) << jobs[k];
    for (int a : alive) {
      const fs::path out = dir_ / "fetched" / (jobs[k] + "-" + std::to_string(a));
      ASSERT_TRUE(through(a).fetch(jobs[k], out).ok()) << jobs[k] << " through " << name(a);
      EXPECT_TRUE(fs::exists(out / "point_cloud.ply"));
      auto metrics = read_file_bytes(out / "metrics.json");
      ASSERT_TRUE(metrics.ok());
      EXPECT_EQ(nlohmann::json::parse(*metrics)["status"], "ok");
    }
  }
}

}  // namespace
}  // namespace gaps

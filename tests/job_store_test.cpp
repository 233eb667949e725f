// The job store's contract, run against both backends: SQLite (a file per test) and PostgreSQL (a private
// server for the suite, a database per test). Queue semantics (claims, leases, takeovers, cancels) and the
// versioned schema are what trainer replicas rely on.
#include <atomic>
#include <set>
#include <thread>

#include <gtest/gtest.h>
#include "absl/strings/match.h"
#include "server/job_store.h"
#include "tests/postgres_server.h"
#include "tests/test_util.h"

namespace gaps {
namespace {

v1::JobStatus queued(const std::string& id, double submitted_at) {
  v1::JobStatus s;
  s.set_job_id(id);
  s.set_state(v1::QUEUED);
  s.set_submitted_at(submitted_at);
  return s;
}

v1::JobEvent closing_for(const v1::JobStatus& status) {
  v1::JobEvent e;
  e.set_job_id(status.job_id());
  *e.mutable_finished() = status;
  return e;
}

class JobStoreContract : public test::TempDirTest, public ::testing::WithParamInterface<std::string> {
 public:
  static void SetUpTestSuite() {
    postgres_dir_ = new std::filesystem::path(std::filesystem::path(::testing::TempDir()) /
                                              absl::StrCat("gaps_job_store_pg_", getpid()));
    std::filesystem::create_directories(*postgres_dir_);
    auto server = test::PostgresServer::start(*postgres_dir_);
    if (server.ok()) postgres_ = server->release();
    postgres_error_ = new absl::Status(server.status());
  }
  static void TearDownTestSuite() {
    delete postgres_;
    postgres_ = nullptr;
    remove_tree(*postgres_dir_);
  }

 protected:
  void SetUp() override {
    test::TempDirTest::SetUp();
    if (GetParam() == "postgresql") {
      ASSERT_NE(postgres_, nullptr) << *postgres_error_;
      database_ = absl::StrCat("t", ++databases_);
      ASSERT_TRUE(postgres_->create_database(database_).ok());
    }
  }
  // A new connection to this test's store (replicas each have their own).
  std::unique_ptr<JobStore> open() {
    auto store = GetParam() == "postgresql" ? JobStore::open_location(postgres_->uri(database_), dir_)
                                            : JobStore::open(dir_ / "jobs.db");
    EXPECT_TRUE(store.ok()) << store.status();
    return store.ok() ? std::move(*store) : nullptr;
  }

  static inline test::PostgresServer* postgres_ = nullptr;
  static inline std::filesystem::path* postgres_dir_ = nullptr;
  static inline absl::Status* postgres_error_ = nullptr;
  static inline int databases_ = 0;
  std::string database_;
};

TEST_P(JobStoreContract, JobsEventsAndArtifactsSurviveReopening) {
  {
    auto store = open();
    ASSERT_NE(store, nullptr);
    v1::JobSpec spec;
    spec.set_name("fern");
    spec.mutable_config()->set_views(3);
    v1::JobStatus status = queued("job-1", 1.0);
    ASSERT_TRUE(store->insert(status, spec).ok());
    EXPECT_FALSE(store->insert(status, spec).ok());  // ids are unique
    status.set_state(v1::RUNNING);
    status.set_iteration(40);
    ASSERT_TRUE(store->update(status).ok());
    for (int i = 0; i < 3; ++i) {
      v1::JobEvent e;
      e.set_job_id("job-1");
      e.mutable_progress()->set_iteration(i * 10);
      auto seq = store->append_event(e);
      ASSERT_TRUE(seq.ok()) << seq.status();
      EXPECT_EQ(*seq, i);
    }
    ASSERT_TRUE(store->set_artifacts("job-1", {{"metrics.json", 10}, {"point_cloud.ply", 2000}}).ok());
  }
  auto store = open();
  ASSERT_NE(store, nullptr);
  auto status = store->get("job-1");
  ASSERT_TRUE(status.ok()) << status.status();
  EXPECT_EQ(status->state(), v1::RUNNING);
  EXPECT_EQ(status->iteration(), 40);
  EXPECT_EQ(store->spec("job-1")->config().views(), 3);
  EXPECT_EQ(store->in_state(v1::RUNNING)->size(), 1u);
  EXPECT_EQ(store->in_state(v1::QUEUED)->size(), 0u);
  auto events = store->events("job-1", 1);
  ASSERT_TRUE(events.ok());
  ASSERT_EQ(events->size(), 2u);
  EXPECT_EQ((*events)[1].progress().iteration(), 20);
  const auto artifacts = store->artifacts("job-1");
  ASSERT_EQ(artifacts->size(), 2u);
  EXPECT_EQ((*artifacts)[1].path, "point_cloud.ply");
  EXPECT_EQ((*artifacts)[1].size, 2000);
  EXPECT_EQ(store->get("job-2").status().code(), absl::StatusCode::kNotFound);
}

TEST_P(JobStoreContract, TheSchemaIsMigratedOnceAndANewerOneIsRefused) {
  auto store = open();
  ASSERT_NE(store, nullptr);
  EXPECT_EQ(*store->schema_version(), 2);
  store.reset();
  store = open();  // reopening applies nothing twice
  ASSERT_NE(store, nullptr);
  EXPECT_EQ(*store->schema_version(), 2);
  store.reset();
  {
    auto driver = GetParam() == "postgresql" ? open_postgres(postgres_->uri(database_))
                                             : open_sqlite((dir_ / "jobs.db").string());
    ASSERT_TRUE(driver.ok());
    ASSERT_TRUE((*driver)->run("INSERT INTO schema_migrations (version, applied_at) VALUES (99, 0)", {}).ok());
  }
  auto newer = GetParam() == "postgresql" ? JobStore::open_location(postgres_->uri(database_), dir_)
                                          : JobStore::open(dir_ / "jobs.db");
  ASSERT_FALSE(newer.ok());
  EXPECT_EQ(newer.status().code(), absl::StatusCode::kFailedPrecondition);
  EXPECT_TRUE(absl::StrContains(newer.status().message(), "schema version 99, newer than this trainer's 2"))
      << newer.status();
}

TEST_P(JobStoreContract, ClaimsTakeTheOldestQueuedJobsOneOwnerEach) {
  auto a = open(), b = open();
  ASSERT_NE(a, nullptr);
  for (int i = 0; i < 3; ++i) ASSERT_TRUE(a->insert(queued(absl::StrCat("job-", i), 10.0 - i), v1::JobSpec()).ok());
  auto first = a->claim("a", 60);
  ASSERT_TRUE(first.ok()) << first.status();
  ASSERT_TRUE(first->has_value());
  EXPECT_EQ((*first)->job_id(), "job-2");  // submitted first
  auto second = b->claim("b", 60);
  ASSERT_TRUE(second.ok() && second->has_value());
  EXPECT_EQ((*second)->job_id(), "job-1");
  ASSERT_TRUE(a->claim("a", 60)->has_value());
  EXPECT_FALSE(b->claim("b", 60)->has_value()) << "every job is leased";
  EXPECT_TRUE(*a->renew("job-2", "a", 60) == false);
  EXPECT_EQ(a->renew("job-1", "a", 60).status().code(), absl::StatusCode::kAborted) << "job-1 is b's";
}

TEST_P(JobStoreContract, AnExpiredLeaseIsTakenOverAndTheOldOwnerCanNoLongerWrite) {
  auto a = open(), b = open();
  ASSERT_NE(a, nullptr);
  ASSERT_TRUE(a->insert(queued("job-1", 1), v1::JobSpec()).ok());
  ASSERT_TRUE(a->claim("a", 0.5)->has_value());
  v1::JobStatus running = queued("job-1", 1);
  running.set_state(v1::RUNNING);
  running.set_iteration(10);
  ASSERT_TRUE(a->update(running, "a").ok());
  EXPECT_FALSE(b->claim("b", 60)->has_value()) << "a's lease is live";
  std::this_thread::sleep_for(std::chrono::milliseconds(700));
  auto taken = b->claim("b", 60);
  ASSERT_TRUE(taken.ok() && taken->has_value()) << taken.status();
  EXPECT_EQ((*taken)->state(), v1::RUNNING) << "a takeover sees the job as its runner left it";
  EXPECT_EQ((*taken)->iteration(), 10);
  EXPECT_EQ(a->renew("job-1", "a", 60).status().code(), absl::StatusCode::kAborted);
  running.set_iteration(20);
  EXPECT_EQ(a->update(running, "a").code(), absl::StatusCode::kAborted);
  v1::JobStatus done = running;
  done.set_state(v1::SUCCEEDED);
  v1::JobEvent closing = closing_for(done);
  EXPECT_EQ(a->end_job(done, {{"point_cloud.ply", 1}}, closing, "a").code(), absl::StatusCode::kAborted);
  EXPECT_EQ(b->get("job-1")->state(), v1::RUNNING) << "the old owner's end stored nothing";
  EXPECT_TRUE(b->events("job-1", 0)->empty());
  EXPECT_TRUE(b->artifacts("job-1")->empty());
  closing = closing_for(done);
  ASSERT_TRUE(b->end_job(done, {{"point_cloud.ply", 1}}, closing, "b").ok());
  EXPECT_EQ(a->get("job-1")->state(), v1::SUCCEEDED);
  EXPECT_EQ(a->events("job-1", 0)->size(), 1u);
  EXPECT_FALSE(a->claim("a", 60)->has_value()) << "an ended job is never claimed";
}

TEST_P(JobStoreContract, AReleasedJobIsTakenOverAtOnce) {
  auto a = open(), b = open();
  ASSERT_NE(a, nullptr);
  ASSERT_TRUE(a->insert(queued("job-1", 1), v1::JobSpec()).ok());
  ASSERT_TRUE(a->claim("a", 600)->has_value());
  ASSERT_TRUE(a->release("job-1", "a").ok());
  EXPECT_TRUE(b->claim("b", 600)->has_value());
  ASSERT_TRUE(b->expire_leases().ok());
  EXPECT_TRUE(a->claim("a", 600)->has_value()) << "expire_leases frees every lease";
}

TEST_P(JobStoreContract, CancelEndsAQueuedJobAndFlagsAClaimedOne) {
  auto store = open();
  ASSERT_NE(store, nullptr);
  ASSERT_TRUE(store->insert(queued("queued", 1), v1::JobSpec()).ok());
  ASSERT_TRUE(store->insert(queued("claimed", 2), v1::JobSpec()).ok());
  v1::JobStatus cancelled = queued("queued", 1);
  cancelled.set_state(v1::CANCELLED);
  v1::JobEvent closing;
  closing.set_job_id("queued");
  *closing.mutable_cancelled() = cancelled;
  auto ended = store->cancel(cancelled, closing);
  ASSERT_TRUE(ended.ok()) << ended.status();
  EXPECT_TRUE(*ended);
  EXPECT_EQ(store->get("queued")->state(), v1::CANCELLED);
  EXPECT_EQ(store->events("queued", 0)->size(), 1u);
  EXPECT_EQ(store->cancel(cancelled, closing).status().code(), absl::StatusCode::kFailedPrecondition);

  auto claimed = store->claim("runner", 60);
  ASSERT_TRUE(claimed.ok() && claimed->has_value());
  EXPECT_EQ((*claimed)->job_id(), "claimed");
  EXPECT_FALSE(*store->renew("claimed", "runner", 60));
  v1::JobStatus request = queued("claimed", 2);
  request.set_state(v1::CANCELLED);
  v1::JobEvent unused;
  unused.set_job_id("claimed");
  auto flagged = store->cancel(request, unused);
  ASSERT_TRUE(flagged.ok());
  EXPECT_FALSE(*flagged) << "its runner ends it";
  EXPECT_EQ(store->get("claimed")->state(), v1::QUEUED);
  EXPECT_TRUE(*store->renew("claimed", "runner", 60)) << "the runner learns of the request at its renewal";
}

TEST_P(JobStoreContract, ConcurrentReplicasNeverClaimTheSameJob) {
  auto setup = open();
  ASSERT_NE(setup, nullptr);
  constexpr int kJobs = 24, kReplicas = 4;
  for (int i = 0; i < kJobs; ++i) ASSERT_TRUE(setup->insert(queued(absl::StrCat("job-", i), i), v1::JobSpec()).ok());
  std::vector<std::unique_ptr<JobStore>> replicas;
  for (int r = 0; r < kReplicas; ++r) replicas.push_back(open());
  std::mutex mutex;
  std::multiset<std::string> claimed;
  std::atomic<int> errors{0};
  std::vector<std::thread> threads;
  for (int r = 0; r < kReplicas; ++r)
    threads.emplace_back([&, r] {
      for (;;) {
        auto job = replicas[r]->claim(absl::StrCat("replica-", r), 600);
        if (!job.ok()) {
          // SQLite's writers queue behind its lock (busy timeout); a refusal here is a real failure.
          if (++errors > 20) return;
          continue;
        }
        if (!job->has_value()) return;
        v1::JobEvent e;  // each claimer writes an event, interleaving with the others' appends
        e.set_job_id((*job)->job_id());
        e.set_log("claimed");
        if (!replicas[r]->append_event(e).ok()) ++errors;
        std::lock_guard<std::mutex> lock(mutex);
        claimed.insert((*job)->job_id());
      }
    });
  for (auto& t : threads) t.join();
  EXPECT_EQ(errors, 0);
  EXPECT_EQ(claimed.size(), static_cast<size_t>(kJobs));
  EXPECT_EQ(std::set<std::string>(claimed.begin(), claimed.end()).size(), static_cast<size_t>(kJobs))
      << "a job was claimed twice";
  for (int i = 0; i < kJobs; ++i) EXPECT_EQ(setup->events(absl::StrCat("job-", i), 0)->size(), 1u);
}

TEST_P(JobStoreContract, EventsOfOneJobFromManyWritersGetGaplessSequences) {
  auto setup = open();
  ASSERT_NE(setup, nullptr);
  ASSERT_TRUE(setup->insert(queued("job-1", 1), v1::JobSpec()).ok());
  constexpr int kWriters = 3, kEach = 20;
  std::vector<std::thread> threads;
  std::atomic<int> errors{0};
  for (int w = 0; w < kWriters; ++w)
    threads.emplace_back([&] {
      auto store = open();
      for (int i = 0; i < kEach; ++i) {
        v1::JobEvent e;
        e.set_job_id("job-1");
        e.set_log("line");
        if (!store->append_event(e).ok()) ++errors;
      }
    });
  for (auto& t : threads) t.join();
  EXPECT_EQ(errors, 0);
  const auto events = setup->events("job-1", 0);
  ASSERT_EQ(events->size(), static_cast<size_t>(kWriters * kEach));
  for (size_t i = 0; i < events->size(); ++i) EXPECT_EQ((*events)[i].sequence(), static_cast<int64_t>(i));
}

INSTANTIATE_TEST_SUITE_P(Backends, JobStoreContract, ::testing::Values("sqlite", "postgresql"),
                         [](const auto& info) { return info.param; });

}  // namespace
}  // namespace gaps

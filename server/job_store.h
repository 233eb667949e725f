#pragma once
// The trainer's job store: jobs with their spec (configuration) and status, each job's event history and
// the artifacts index, in SQLite (one trainer, embedded; the default) or PostgreSQL (any number of trainer
// replicas sharing one queue), behind server/sql_driver.h. The schema is versioned and migrated at opening.
//
// The queue: a replica claims the oldest job that is queued, or running under an expired lease, and holds a
// lease on it that it renews by heartbeat; writes that only the runner may make (progress, the job's end)
// name their owner and are refused (ABORTED) once another replica took the job over, so a job ends once.
// Cancel requests and events go through the store, so every replica serves every job.
//
// Thread-safe (one connection behind a mutex). Errors carry the database's message and say what a caller
// can do: UNAVAILABLE (locked, busy, connection lost: try again), RESOURCE_EXHAUSTED (disk full),
// PERMISSION_DENIED (read-only), ABORTED (the lease is another replica's).
#include <filesystem>
#include <functional>
#include <memory>
#include <mutex>
#include <optional>
#include <string>
#include <vector>

#include "absl/status/statusor.h"
#include "gaps/v1/trainer.pb.h"
#include "server/sql_driver.h"

namespace gaps {

class JobStore {
 public:
  // SQLite at `file`.
  static absl::StatusOr<std::unique_ptr<JobStore>> open(const std::filesystem::path& file);
  // `location`: "" (SQLite at DATA_DIR/jobs.db) or a PostgreSQL URI ("postgresql://..." / "postgres://...").
  static absl::StatusOr<std::unique_ptr<JobStore>> open_location(const std::string& location,
                                                                 const std::filesystem::path& data_dir);
  static absl::StatusOr<std::unique_ptr<JobStore>> open_driver(std::unique_ptr<SqlDriver> driver, bool shared);

  // Whether other trainer processes may use this store (and the data folder) at the same time.
  bool shared() const { return shared_; }
  std::string describe() const { return driver_->describe(); }
  // The schema version the store is at (the number of migrations applied).
  absl::StatusOr<int> schema_version();

  absl::Status insert(const v1::JobStatus& status, const v1::JobSpec& spec);
  // With an `owner`: only while it holds the job's lease (ABORTED otherwise).
  absl::Status update(const v1::JobStatus& status, const std::string& owner = "");
  absl::StatusOr<v1::JobStatus> get(const std::string& job_id);
  absl::StatusOr<v1::JobSpec> spec(const std::string& job_id);
  // Every job, oldest first.
  absl::StatusOr<std::vector<v1::JobStatus>> list();
  absl::StatusOr<std::vector<v1::JobStatus>> in_state(v1::JobState state);

  // Stores the event with the job's next sequence number (set in `event`) and returns it.
  absl::StatusOr<int64_t> append_event(v1::JobEvent& event);
  absl::StatusOr<std::vector<v1::JobEvent>> events(const std::string& job_id, int64_t from_sequence);

  struct Artifact {
    std::string path;  // relative to the job's output folder
    int64_t size = 0;
  };
  absl::Status set_artifacts(const std::string& job_id, const std::vector<Artifact>& artifacts);
  absl::StatusOr<std::vector<Artifact>> artifacts(const std::string& job_id);

  // Records a job's end in one transaction: its final status, its artifacts and the closing event (whose
  // sequence number it sets), and drops its lease. Either all of it is stored or none, so the store never
  // holds an ended job whose watchers would wait for a closing event forever, nor a closing event of a job
  // still running. With an `owner`: only while it holds the lease (ABORTED otherwise, storing nothing).
  absl::Status end_job(const v1::JobStatus& status, const std::vector<Artifact>& artifacts, v1::JobEvent& event,
                       const std::string& owner = "");

  // The oldest job that is QUEUED, or RUNNING with an expired lease, now leased to `owner` for
  // `lease_seconds` by the store's clock; nullopt when there is none. The status is as stored (a RUNNING one
  // is a takeover: its runner died or stopped).
  absl::StatusOr<std::optional<v1::JobStatus>> claim(const std::string& owner, double lease_seconds);
  // Extends the lease of `owner`; ABORTED when it no longer holds it. True when a cancel was requested.
  absl::StatusOr<bool> renew(const std::string& job_id, const std::string& owner, double lease_seconds);
  // Gives the lease up at once (a clean stop), so that another replica may go on with the job.
  absl::Status release(const std::string& job_id, const std::string& owner);
  // Every lease expires now: for a store no other process uses, whose leases died with an earlier process.
  absl::Status expire_leases();
  // Cancels a job: one that nobody runs (QUEUED, no live lease) ends here as `cancelled` with `closing`
  // (true); for one that runs, the request is recorded for its runner (false), which sees it at its next
  // renewal. FAILED_PRECONDITION for a job that already ended.
  absl::StatusOr<bool> cancel(const v1::JobStatus& cancelled, v1::JobEvent& closing);

 private:
  JobStore(std::unique_ptr<SqlDriver> driver, bool shared) : driver_(std::move(driver)), shared_(shared) {}
  absl::Status migrate();
  // Runs `body` in one transaction, rolling back when it or the commit fails.
  absl::Status transaction(const std::function<absl::Status()>& body);
  // The writes without the lock, for use inside a transaction.
  absl::Status update_locked(const v1::JobStatus& status, const std::string& owner);
  absl::Status append_event_locked(v1::JobEvent& event);
  absl::Status set_artifacts_locked(const std::string& job_id, const std::vector<Artifact>& artifacts);
  absl::StatusOr<std::vector<v1::JobStatus>> statuses(absl::string_view sql, const std::vector<SqlParam>& params);

  std::unique_ptr<SqlDriver> driver_;
  bool shared_;
  std::mutex mutex_;
};

}  // namespace gaps

#pragma once
// The trainer's job store: an SQLite database (jobs with their spec, i.e. configuration, and status;
// each job's event history; the artifacts index) that survives restarts. Thread-safe: one connection
// behind a mutex, WAL journal so readers do not block the writer for long. Errors carry the store's
// message and say what a caller can do about them: UNAVAILABLE for a database another process keeps locked
// (try again), RESOURCE_EXHAUSTED for a full disk, PERMISSION_DENIED for a read-only database.
#include <filesystem>
#include <functional>
#include <memory>
#include <mutex>
#include <string>
#include <vector>

#include "absl/status/statusor.h"
#include "gaps/v1/trainer.pb.h"

struct sqlite3;

namespace gaps {

class JobStore {
 public:
  static absl::StatusOr<std::unique_ptr<JobStore>> open(const std::filesystem::path& file);
  ~JobStore();

  absl::Status insert(const v1::JobStatus& status, const v1::JobSpec& spec);
  absl::Status update(const v1::JobStatus& status);
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
  // sequence number it sets). Either all of it is stored or none, so the store never holds an ended job
  // whose watchers would wait for a closing event forever, nor a closing event of a job still running.
  absl::Status end_job(const v1::JobStatus& status, const std::vector<Artifact>& artifacts, v1::JobEvent& event);

 private:
  explicit JobStore(sqlite3* db) : db_(db) {}
  absl::Status exec(const std::string& sql);
  // Runs `body` between BEGIN IMMEDIATE and COMMIT, rolling back when either fails.
  absl::Status transaction(const std::function<absl::Status()>& body);
  // The writes without the lock, for use inside a transaction.
  absl::Status update_locked(const v1::JobStatus& status);
  absl::Status append_event_locked(v1::JobEvent& event);
  absl::Status set_artifacts_locked(const std::string& job_id, const std::vector<Artifact>& artifacts);

  sqlite3* db_;
  std::mutex mutex_;
};

}  // namespace gaps

#include "server/job_store.h"

#include "absl/strings/match.h"
#include "absl/strings/str_cat.h"
#include "common/error_kind.h"
#include "common/status_macros.h"

namespace gaps {
namespace {

// Migration N brings the schema from version N-1 to N; a store records each it applied. Never edit one
// that has shipped: add the next.
constexpr const char* kMigrations[] = {
    // 1: jobs, their events and artifacts (the schema before versioning; IF NOT EXISTS adopts such stores).
    R"sql(
CREATE TABLE IF NOT EXISTS jobs (
  id TEXT PRIMARY KEY,
  state INTEGER NOT NULL,
  submitted_at {REAL} NOT NULL,
  spec {BLOB} NOT NULL,    -- gaps.v1.JobSpec: name, TrainConfig, cameras
  status {BLOB} NOT NULL   -- gaps.v1.JobStatus
);
CREATE TABLE IF NOT EXISTS events (
  job_id TEXT NOT NULL REFERENCES jobs(id),
  seq BIGINT NOT NULL,
  event {BLOB} NOT NULL,   -- gaps.v1.JobEvent
  PRIMARY KEY (job_id, seq)
);
CREATE TABLE IF NOT EXISTS artifacts (
  job_id TEXT NOT NULL REFERENCES jobs(id),
  path TEXT NOT NULL,
  size BIGINT NOT NULL,
  PRIMARY KEY (job_id, path)
);
)sql",
    // 2: leases and cancel requests, so that replicas share the queue.
    R"sql(
ALTER TABLE jobs ADD COLUMN lease_owner TEXT;
ALTER TABLE jobs ADD COLUMN lease_expires {REAL};
ALTER TABLE jobs ADD COLUMN cancel_requested INTEGER NOT NULL DEFAULT 0;
CREATE INDEX IF NOT EXISTS jobs_by_state ON jobs (state, submitted_at);
)sql",
};
constexpr int kSchemaVersion = sizeof(kMigrations) / sizeof(kMigrations[0]);

bool terminal(int64_t state) { return state == v1::SUCCEEDED || state == v1::FAILED || state == v1::CANCELLED; }

template <typename Message>
absl::StatusOr<Message> parse(const std::optional<std::string>& bytes, const std::string& what) {
  Message m;
  if (!bytes || !m.ParseFromString(*bytes)) return absl::DataLossError(absl::StrCat("job store: corrupt ", what));
  return m;
}

absl::Status no_job(const std::string& job_id) { return absl::NotFoundError(absl::StrCat("no job '", job_id, "'")); }

absl::Status lease_lost(const std::string& job_id, const std::string& owner) {
  return absl::AbortedError(absl::StrCat("job ", job_id, ": trainer ", owner,
                                         " no longer holds its lease (another trainer took it over, or it ended)"));
}

}  // namespace

absl::StatusOr<std::unique_ptr<JobStore>> JobStore::open(const std::filesystem::path& file) {
  // A folder where the database belongs is a mistake in the data folder, not an unreachable service.
  if (std::error_code ec; std::filesystem::is_directory(file, ec))
    return input_data_error(absl::FailedPreconditionError(
        absl::StrCat("job store ", file.string(), " is a folder, not a job database (move it away)")));
  GAPS_ASSIGN_OR_RETURN(std::unique_ptr<SqlDriver> driver, open_sqlite(file.string()));
  return open_driver(std::move(driver), false);
}

absl::StatusOr<std::unique_ptr<JobStore>> JobStore::open_location(const std::string& location,
                                                                  const std::filesystem::path& data_dir) {
  if (location.empty() || location == "sqlite") return open(data_dir / "jobs.db");
  if (absl::StartsWith(location, "postgresql://") || absl::StartsWith(location, "postgres://")) {
    GAPS_ASSIGN_OR_RETURN(std::unique_ptr<SqlDriver> driver, open_postgres(location));
    return open_driver(std::move(driver), true);
  }
  return absl::InvalidArgumentError(
      "--job_store must be empty (SQLite in the data folder) or a PostgreSQL URI (postgresql://USER:PASSWORD@HOST/DB)");
}

absl::StatusOr<std::unique_ptr<JobStore>> JobStore::open_driver(std::unique_ptr<SqlDriver> driver, bool shared) {
  std::unique_ptr<JobStore> store(new JobStore(std::move(driver), shared));
  GAPS_RETURN_IF_ERROR(store->migrate());
  return store;
}

absl::Status JobStore::transaction(const std::function<absl::Status()>& body) {
  GAPS_RETURN_IF_ERROR(driver_->begin());
  absl::Status status = body();
  if (status.ok()) status = driver_->run("COMMIT").status();
  if (!status.ok()) {
    if (absl::Status undo = driver_->rollback(); !undo.ok())
      status =
          absl::Status(status.code(), absl::StrCat(status.message(), "; rolling back failed too: ", undo.message()));
  }
  return status;
}

absl::Status JobStore::migrate() {
  std::lock_guard<std::mutex> lock(mutex_);
  return transaction([&]() -> absl::Status {
    // Replicas starting together migrate one after the other (PostgreSQL: a transaction-scoped advisory
    // lock; SQLite: the immediate transaction itself).
    if (shared_) GAPS_RETURN_IF_ERROR(driver_->run("SELECT pg_advisory_xact_lock(4702751)", {}).status());
    GAPS_RETURN_IF_ERROR(driver_
                             ->run("CREATE TABLE IF NOT EXISTS schema_migrations (version INTEGER PRIMARY KEY, "
                                   "applied_at {REAL} NOT NULL)",
                                   {})
                             .status());
    GAPS_ASSIGN_OR_RETURN(SqlResult r, driver_->run("SELECT COALESCE(MAX(version), 0) FROM schema_migrations", {}));
    const int64_t version = sql_int(r.rows.at(0).at(0));
    if (version > kSchemaVersion)
      return absl::FailedPreconditionError(absl::StrCat("job store ", driver_->describe(), " is at schema version ",
                                                        version, ", newer than this trainer's ", kSchemaVersion,
                                                        ": upgrade the trainer"));
    for (int64_t next = version + 1; next <= kSchemaVersion; ++next) {
      const absl::Status applied = driver_->run(kMigrations[next - 1]).status();
      if (!applied.ok())
        return absl::Status(applied.code(), absl::StrCat("job store migration ", next, ": ", applied.message()));
      GAPS_RETURN_IF_ERROR(
          driver_->run("INSERT INTO schema_migrations (version, applied_at) VALUES ($1, {NOW})", {SqlParam::Int(next)})
              .status());
    }
    return absl::OkStatus();
  });
}

absl::StatusOr<int> JobStore::schema_version() {
  std::lock_guard<std::mutex> lock(mutex_);
  GAPS_ASSIGN_OR_RETURN(SqlResult r, driver_->run("SELECT COALESCE(MAX(version), 0) FROM schema_migrations", {}));
  return static_cast<int>(sql_int(r.rows.at(0).at(0)));
}

absl::Status JobStore::insert(const v1::JobStatus& status, const v1::JobSpec& spec) {
  std::lock_guard<std::mutex> lock(mutex_);
  return driver_
      ->run("INSERT INTO jobs (id, state, submitted_at, spec, status) VALUES ($1, $2, $3, $4, $5)",
            {SqlParam::Text(status.job_id()), SqlParam::Int(status.state()), SqlParam::Real(status.submitted_at()),
             SqlParam::Blob(spec.SerializeAsString()), SqlParam::Blob(status.SerializeAsString())})
      .status();
}

absl::Status JobStore::update(const v1::JobStatus& status, const std::string& owner) {
  std::lock_guard<std::mutex> lock(mutex_);
  return update_locked(status, owner);
}

absl::Status JobStore::update_locked(const v1::JobStatus& status, const std::string& owner) {
  GAPS_ASSIGN_OR_RETURN(
      SqlResult r,
      driver_->run("UPDATE jobs SET state = $1, status = $2 WHERE id = $3 AND ($4 = '' OR lease_owner = $4)",
                   {SqlParam::Int(status.state()), SqlParam::Blob(status.SerializeAsString()),
                    SqlParam::Text(status.job_id()), SqlParam::Text(owner)}));
  if (r.affected > 0) return absl::OkStatus();
  GAPS_ASSIGN_OR_RETURN(SqlResult exists,
                        driver_->run("SELECT 1 FROM jobs WHERE id = $1", {SqlParam::Text(status.job_id())}));
  return exists.rows.empty() ? no_job(status.job_id()) : lease_lost(status.job_id(), owner);
}

absl::StatusOr<v1::JobStatus> JobStore::get(const std::string& job_id) {
  std::lock_guard<std::mutex> lock(mutex_);
  GAPS_ASSIGN_OR_RETURN(SqlResult r, driver_->run("SELECT status FROM jobs WHERE id = $1", {SqlParam::Text(job_id)}));
  if (r.rows.empty()) return no_job(job_id);
  return parse<v1::JobStatus>(r.rows[0][0], absl::StrCat("status record of job ", job_id, " in ", driver_->describe()));
}

absl::StatusOr<v1::JobSpec> JobStore::spec(const std::string& job_id) {
  std::lock_guard<std::mutex> lock(mutex_);
  GAPS_ASSIGN_OR_RETURN(SqlResult r, driver_->run("SELECT spec FROM jobs WHERE id = $1", {SqlParam::Text(job_id)}));
  if (r.rows.empty()) return no_job(job_id);
  return parse<v1::JobSpec>(r.rows[0][0], absl::StrCat("spec of job ", job_id, " in ", driver_->describe()));
}

absl::StatusOr<std::vector<v1::JobStatus>> JobStore::statuses(absl::string_view sql,
                                                              const std::vector<SqlParam>& params) {
  std::lock_guard<std::mutex> lock(mutex_);
  GAPS_ASSIGN_OR_RETURN(SqlResult r, driver_->run(sql, params));
  std::vector<v1::JobStatus> out;
  for (const auto& row : r.rows) {
    GAPS_ASSIGN_OR_RETURN(v1::JobStatus status, parse<v1::JobStatus>(row[0], "job status"));
    out.push_back(std::move(status));
  }
  return out;
}

absl::StatusOr<std::vector<v1::JobStatus>> JobStore::list() {
  std::lock_guard<std::mutex> lock(mutex_);
  GAPS_ASSIGN_OR_RETURN(SqlResult r, driver_->run("SELECT status, id FROM jobs ORDER BY submitted_at, id", {}));
  std::vector<v1::JobStatus> out;
  for (const auto& row : r.rows) {
    const std::string id = row[1].value_or("");
    absl::StatusOr<v1::JobStatus> status =
        parse<v1::JobStatus>(row[0], absl::StrCat("status record of job ", id, " in ", driver_->describe()));
    if (status.ok()) {
      out.push_back(*std::move(status));
      continue;
    }
    // One unreadable row must not hide every other job: it is listed as failed, saying why and where.
    v1::JobStatus unreadable;
    unreadable.set_job_id(id);
    unreadable.set_state(v1::FAILED);
    unreadable.set_error(std::string(status.status().message()));
    out.push_back(std::move(unreadable));
  }
  return out;
}

absl::StatusOr<std::vector<v1::JobStatus>> JobStore::in_state(v1::JobState state) {
  return statuses("SELECT status FROM jobs WHERE state = $1 ORDER BY submitted_at, id", {SqlParam::Int(state)});
}

absl::StatusOr<int64_t> JobStore::append_event(v1::JobEvent& event) {
  std::lock_guard<std::mutex> lock(mutex_);
  GAPS_RETURN_IF_ERROR(transaction([&] { return append_event_locked(event); }));
  return event.sequence();
}

absl::Status JobStore::append_event_locked(v1::JobEvent& event) {
  const SqlParam job = SqlParam::Text(event.job_id());
  // Appenders of one job (its runner, a submitting or cancelling replica) take their numbers in turn.
  GAPS_RETURN_IF_ERROR(driver_->run("SELECT id FROM jobs WHERE id = $1 {LOCK}", {job}).status());
  GAPS_ASSIGN_OR_RETURN(SqlResult next,
                        driver_->run("SELECT COALESCE(MAX(seq) + 1, 0) FROM events WHERE job_id = $1", {job}));
  event.set_sequence(sql_int(next.rows.at(0).at(0)));
  return driver_
      ->run("INSERT INTO events (job_id, seq, event) VALUES ($1, $2, $3)",
            {job, SqlParam::Int(event.sequence()), SqlParam::Blob(event.SerializeAsString())})
      .status();
}

absl::StatusOr<std::vector<v1::JobEvent>> JobStore::events(const std::string& job_id, int64_t from_sequence) {
  std::lock_guard<std::mutex> lock(mutex_);
  GAPS_ASSIGN_OR_RETURN(SqlResult r,
                        driver_->run("SELECT event FROM events WHERE job_id = $1 AND seq >= $2 ORDER BY seq",
                                     {SqlParam::Text(job_id), SqlParam::Int(from_sequence)}));
  std::vector<v1::JobEvent> out;
  for (const auto& row : r.rows) {
    GAPS_ASSIGN_OR_RETURN(v1::JobEvent e, parse<v1::JobEvent>(row[0], "job event"));
    out.push_back(std::move(e));
  }
  return out;
}

absl::Status JobStore::set_artifacts(const std::string& job_id, const std::vector<Artifact>& artifacts) {
  std::lock_guard<std::mutex> lock(mutex_);
  return transaction([&] { return set_artifacts_locked(job_id, artifacts); });
}

absl::Status JobStore::set_artifacts_locked(const std::string& job_id, const std::vector<Artifact>& artifacts) {
  GAPS_RETURN_IF_ERROR(driver_->run("DELETE FROM artifacts WHERE job_id = $1", {SqlParam::Text(job_id)}).status());
  for (const auto& a : artifacts)
    GAPS_RETURN_IF_ERROR(driver_
                             ->run("INSERT INTO artifacts (job_id, path, size) VALUES ($1, $2, $3)",
                                   {SqlParam::Text(job_id), SqlParam::Text(a.path), SqlParam::Int(a.size)})
                             .status());
  return absl::OkStatus();
}

absl::Status JobStore::end_job(const v1::JobStatus& status, const std::vector<Artifact>& artifacts, v1::JobEvent& event,
                               const std::string& owner) {
  std::lock_guard<std::mutex> lock(mutex_);
  return transaction([&]() -> absl::Status {
    GAPS_RETURN_IF_ERROR(update_locked(status, owner));
    GAPS_RETURN_IF_ERROR(set_artifacts_locked(status.job_id(), artifacts));
    GAPS_RETURN_IF_ERROR(driver_
                             ->run("UPDATE jobs SET lease_owner = NULL, lease_expires = NULL WHERE id = $1",
                                   {SqlParam::Text(status.job_id())})
                             .status());
    return append_event_locked(event);
  });
}

absl::StatusOr<std::vector<JobStore::Artifact>> JobStore::artifacts(const std::string& job_id) {
  std::lock_guard<std::mutex> lock(mutex_);
  GAPS_ASSIGN_OR_RETURN(SqlResult r, driver_->run("SELECT path, size FROM artifacts WHERE job_id = $1 ORDER BY path",
                                                  {SqlParam::Text(job_id)}));
  std::vector<Artifact> out;
  for (const auto& row : r.rows) out.push_back({row[0].value_or(""), sql_int(row[1])});
  return out;
}

absl::StatusOr<std::optional<v1::JobStatus>> JobStore::claim(const std::string& owner, double lease_seconds) {
  std::lock_guard<std::mutex> lock(mutex_);
  std::optional<v1::JobStatus> claimed;
  GAPS_RETURN_IF_ERROR(transaction([&]() -> absl::Status {
    // Replicas claiming at once skip each other's rows instead of waiting for them.
    GAPS_ASSIGN_OR_RETURN(SqlResult next,
                          driver_->run("SELECT id, status FROM jobs WHERE state IN ($1, $2) AND (lease_expires IS NULL "
                                       "OR lease_expires < {NOW}) ORDER BY submitted_at, id LIMIT 1 {SKIP_LOCKED}",
                                       {SqlParam::Int(v1::QUEUED), SqlParam::Int(v1::RUNNING)}));
    if (next.rows.empty()) return absl::OkStatus();
    GAPS_RETURN_IF_ERROR(
        driver_
            ->run("UPDATE jobs SET lease_owner = $1, lease_expires = {NOW} + $2 WHERE id = $3",
                  {SqlParam::Text(owner), SqlParam::Real(lease_seconds), SqlParam::Text(next.rows[0][0].value_or(""))})
            .status());
    GAPS_ASSIGN_OR_RETURN(claimed, parse<v1::JobStatus>(next.rows[0][1], "job status"));
    return absl::OkStatus();
  }));
  return claimed;
}

absl::StatusOr<bool> JobStore::renew(const std::string& job_id, const std::string& owner, double lease_seconds) {
  std::lock_guard<std::mutex> lock(mutex_);
  GAPS_ASSIGN_OR_RETURN(SqlResult r,
                        driver_->run("UPDATE jobs SET lease_expires = {NOW} + $1 WHERE id = $2 AND "
                                     "lease_owner = $3 RETURNING cancel_requested",
                                     {SqlParam::Real(lease_seconds), SqlParam::Text(job_id), SqlParam::Text(owner)}));
  if (r.rows.empty()) return lease_lost(job_id, owner);
  return sql_int(r.rows[0][0]) != 0;
}

absl::Status JobStore::release(const std::string& job_id, const std::string& owner) {
  std::lock_guard<std::mutex> lock(mutex_);
  return driver_
      ->run("UPDATE jobs SET lease_owner = NULL, lease_expires = NULL WHERE id = $1 AND lease_owner = $2",
            {SqlParam::Text(job_id), SqlParam::Text(owner)})
      .status();
}

absl::Status JobStore::expire_leases() {
  std::lock_guard<std::mutex> lock(mutex_);
  return driver_->run("UPDATE jobs SET lease_owner = NULL, lease_expires = NULL WHERE lease_owner IS NOT NULL", {})
      .status();
}

absl::StatusOr<bool> JobStore::cancel(const v1::JobStatus& cancelled, v1::JobEvent& closing) {
  std::lock_guard<std::mutex> lock(mutex_);
  bool ended = false;
  GAPS_RETURN_IF_ERROR(transaction([&]() -> absl::Status {
    const SqlParam job = SqlParam::Text(cancelled.job_id());
    GAPS_ASSIGN_OR_RETURN(SqlResult r,
                          driver_->run("SELECT state, lease_expires, {NOW} FROM jobs WHERE id = $1 {LOCK}", {job}));
    if (r.rows.empty()) return no_job(cancelled.job_id());
    const int64_t state = sql_int(r.rows[0][0]);
    if (terminal(state))
      return absl::FailedPreconditionError(absl::StrCat("job ", cancelled.job_id(), " already ended (",
                                                        v1::JobState_Name(static_cast<v1::JobState>(state)), ")"));
    const bool leased = r.rows[0][1].has_value() && sql_real(r.rows[0][1]) >= sql_real(r.rows[0][2]);
    if (state == v1::QUEUED && !leased) {
      GAPS_RETURN_IF_ERROR(update_locked(cancelled, ""));
      ended = true;
      return append_event_locked(closing);
    }
    return driver_->run("UPDATE jobs SET cancel_requested = 1 WHERE id = $1", {job}).status();
  }));
  return ended;
}

}  // namespace gaps

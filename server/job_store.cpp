#include "server/job_store.h"

#include <sqlite3.h>

#include "absl/strings/str_cat.h"
#include "common/status_macros.h"

namespace gaps {
namespace {

constexpr char kSchema[] = R"sql(
CREATE TABLE IF NOT EXISTS jobs (
  id TEXT PRIMARY KEY,
  state INTEGER NOT NULL,
  submitted_at REAL NOT NULL,
  spec BLOB NOT NULL,    -- gaps.v1.JobSpec: name, TrainConfig, cameras
  status BLOB NOT NULL   -- gaps.v1.JobStatus
);
CREATE TABLE IF NOT EXISTS events (
  job_id TEXT NOT NULL REFERENCES jobs(id),
  seq INTEGER NOT NULL,
  event BLOB NOT NULL,   -- gaps.v1.JobEvent
  PRIMARY KEY (job_id, seq)
);
CREATE TABLE IF NOT EXISTS artifacts (
  job_id TEXT NOT NULL REFERENCES jobs(id),
  path TEXT NOT NULL,
  size INTEGER NOT NULL,
  PRIMARY KEY (job_id, path)
);
)sql";

// The code says whether trying again can help; the message is SQLite's.
absl::Status sqlite_error(int rc, absl::string_view message) {
  const std::string text = absl::StrCat("job store: ", message);
  switch (rc & 0xff) {  // the primary result code
    case SQLITE_BUSY:
    case SQLITE_LOCKED:
      return absl::UnavailableError(text);
    case SQLITE_FULL:
      return absl::ResourceExhaustedError(text);
    case SQLITE_READONLY:
    case SQLITE_PERM:
      return absl::PermissionDeniedError(text);
    default:
      return absl::InternalError(text);
  }
}

// A prepared statement that finalises itself. A failed preparation or binding is kept and reported by
// done(), and step() does not run the statement after one.
class Statement {
 public:
  Statement(sqlite3* db, const char* sql) : db_(db) { check(sqlite3_prepare_v2(db, sql, -1, &stmt_, nullptr)); }
  // Finalising reports the last step's error again, which done() already returned.
  ~Statement() { sqlite3_finalize(stmt_); }
  absl::Status prepared() const { return error_; }
  void bind(int i, const std::string& text) {
    check(sqlite3_bind_text64(stmt_, i, text.data(), text.size(), SQLITE_TRANSIENT, SQLITE_UTF8));
  }
  void bind_blob(int i, const std::string& bytes) {
    check(sqlite3_bind_blob64(stmt_, i, bytes.data(), bytes.size(), SQLITE_TRANSIENT));
  }
  void bind(int i, int64_t v) { check(sqlite3_bind_int64(stmt_, i, v)); }
  void bind(int i, double v) { check(sqlite3_bind_double(stmt_, i, v)); }
  // SQLITE_ROW, SQLITE_DONE or an error code.
  int step() { return error_.ok() ? sqlite3_step(stmt_) : SQLITE_ERROR; }
  absl::Status done(int rc) const {
    if (!error_.ok()) return error_;
    return rc == SQLITE_DONE || rc == SQLITE_ROW ? absl::OkStatus() : sqlite_error(rc, sqlite3_errmsg(db_));
  }
  std::string blob(int column) const {
    const void* p = sqlite3_column_blob(stmt_, column);
    return p ? std::string(static_cast<const char*>(p), sqlite3_column_bytes(stmt_, column)) : std::string();
  }
  std::string text(int column) const {
    const unsigned char* p = sqlite3_column_text(stmt_, column);
    return p ? std::string(reinterpret_cast<const char*>(p)) : std::string();
  }
  int64_t integer(int column) const { return sqlite3_column_int64(stmt_, column); }

 private:
  // Keeps the first failure: the message of a later successful call would replace SQLite's.
  void check(int rc) {
    if (rc != SQLITE_OK && error_.ok()) error_ = sqlite_error(rc, sqlite3_errmsg(db_));
  }

  sqlite3* db_;
  sqlite3_stmt* stmt_ = nullptr;
  absl::Status error_;
};

template <typename Message>
absl::StatusOr<Message> parse(const std::string& bytes, const std::string& what) {
  Message m;
  if (!m.ParseFromString(bytes)) return absl::DataLossError(absl::StrCat("job store: corrupt ", what));
  return m;
}

absl::StatusOr<std::vector<v1::JobStatus>> read_statuses(Statement& s) {
  GAPS_RETURN_IF_ERROR(s.prepared());
  std::vector<v1::JobStatus> out;
  int rc;
  while ((rc = s.step()) == SQLITE_ROW) {
    GAPS_ASSIGN_OR_RETURN(v1::JobStatus status, parse<v1::JobStatus>(s.blob(0), "job status"));
    out.push_back(std::move(status));
  }
  GAPS_RETURN_IF_ERROR(s.done(rc));
  return out;
}

}  // namespace

absl::StatusOr<std::unique_ptr<JobStore>> JobStore::open(const std::filesystem::path& file) {
  sqlite3* db = nullptr;
  if (sqlite3_open(file.c_str(), &db) != SQLITE_OK) {
    const std::string message = db ? sqlite3_errmsg(db) : "out of memory";
    sqlite3_close(db);
    return absl::UnavailableError(absl::StrCat(file.string(), ": cannot open job database (", message, ")"));
  }
  std::unique_ptr<JobStore> store(new JobStore(db));
  // SQLite falls back to read-only for a file it may not write; every job would then fail at its first
  // write instead of the trainer at its start.
  if (sqlite3_db_readonly(db, "main") == 1)
    return absl::PermissionDeniedError(absl::StrCat(file.string(), ": the job database is read-only"));
  sqlite3_busy_timeout(db, 5000);
  // WAL with synchronous=NORMAL: no fsync per event; a killed process loses nothing, a power loss at most
  // the last transactions, and the database stays consistent either way.
  GAPS_RETURN_IF_ERROR(store->exec("PRAGMA journal_mode=WAL; PRAGMA synchronous=NORMAL; PRAGMA foreign_keys=ON;"));
  GAPS_RETURN_IF_ERROR(store->exec(kSchema));
  return store;
}

JobStore::~JobStore() { sqlite3_close(db_); }

absl::Status JobStore::exec(const std::string& sql) {
  char* error = nullptr;
  const int rc = sqlite3_exec(db_, sql.c_str(), nullptr, nullptr, &error);
  if (rc == SQLITE_OK) return absl::OkStatus();
  const std::string message = error ? error : sqlite3_errstr(rc);
  sqlite3_free(error);
  return sqlite_error(rc, message);
}

absl::Status JobStore::transaction(const std::function<absl::Status()>& body) {
  GAPS_RETURN_IF_ERROR(exec("BEGIN IMMEDIATE"));
  absl::Status status = body();
  if (status.ok()) status = exec("COMMIT");
  // A failed COMMIT can leave the transaction open: every later write would join it and be lost with it.
  if (!status.ok() && sqlite3_get_autocommit(db_) == 0) {
    if (absl::Status undo = exec("ROLLBACK"); !undo.ok())
      status =
          absl::Status(status.code(), absl::StrCat(status.message(), "; rolling back failed too: ", undo.message()));
  }
  return status;
}

absl::Status JobStore::insert(const v1::JobStatus& status, const v1::JobSpec& spec) {
  std::lock_guard<std::mutex> lock(mutex_);
  Statement s(db_, "INSERT INTO jobs (id, state, submitted_at, spec, status) VALUES (?, ?, ?, ?, ?)");
  GAPS_RETURN_IF_ERROR(s.prepared());
  s.bind(1, status.job_id());
  s.bind(2, int64_t{status.state()});
  s.bind(3, status.submitted_at());
  s.bind_blob(4, spec.SerializeAsString());
  s.bind_blob(5, status.SerializeAsString());
  return s.done(s.step());
}

absl::Status JobStore::update(const v1::JobStatus& status) {
  std::lock_guard<std::mutex> lock(mutex_);
  return update_locked(status);
}

absl::Status JobStore::update_locked(const v1::JobStatus& status) {
  Statement s(db_, "UPDATE jobs SET state = ?, status = ? WHERE id = ?");
  GAPS_RETURN_IF_ERROR(s.prepared());
  s.bind(1, int64_t{status.state()});
  s.bind_blob(2, status.SerializeAsString());
  s.bind(3, status.job_id());
  GAPS_RETURN_IF_ERROR(s.done(s.step()));
  if (sqlite3_changes(db_) == 0) return absl::NotFoundError(absl::StrCat("no job '", status.job_id(), "'"));
  return absl::OkStatus();
}

absl::StatusOr<v1::JobStatus> JobStore::get(const std::string& job_id) {
  std::lock_guard<std::mutex> lock(mutex_);
  Statement s(db_, "SELECT status FROM jobs WHERE id = ?");
  GAPS_RETURN_IF_ERROR(s.prepared());
  s.bind(1, job_id);
  const int rc = s.step();
  if (rc == SQLITE_DONE) return absl::NotFoundError(absl::StrCat("no job '", job_id, "'"));
  GAPS_RETURN_IF_ERROR(s.done(rc));
  return parse<v1::JobStatus>(s.blob(0), "job status");
}

absl::StatusOr<v1::JobSpec> JobStore::spec(const std::string& job_id) {
  std::lock_guard<std::mutex> lock(mutex_);
  Statement s(db_, "SELECT spec FROM jobs WHERE id = ?");
  GAPS_RETURN_IF_ERROR(s.prepared());
  s.bind(1, job_id);
  const int rc = s.step();
  if (rc == SQLITE_DONE) return absl::NotFoundError(absl::StrCat("no job '", job_id, "'"));
  GAPS_RETURN_IF_ERROR(s.done(rc));
  return parse<v1::JobSpec>(s.blob(0), "job spec");
}

absl::StatusOr<std::vector<v1::JobStatus>> JobStore::list() {
  std::lock_guard<std::mutex> lock(mutex_);
  Statement s(db_, "SELECT status FROM jobs ORDER BY submitted_at, id");
  return read_statuses(s);
}

absl::StatusOr<std::vector<v1::JobStatus>> JobStore::in_state(v1::JobState state) {
  std::lock_guard<std::mutex> lock(mutex_);
  Statement s(db_, "SELECT status FROM jobs WHERE state = ? ORDER BY submitted_at, id");
  GAPS_RETURN_IF_ERROR(s.prepared());
  s.bind(1, int64_t{state});
  return read_statuses(s);
}

absl::StatusOr<int64_t> JobStore::append_event(v1::JobEvent& event) {
  std::lock_guard<std::mutex> lock(mutex_);
  GAPS_RETURN_IF_ERROR(transaction([&] { return append_event_locked(event); }));
  return event.sequence();
}

absl::Status JobStore::append_event_locked(v1::JobEvent& event) {
  {
    Statement next(db_, "SELECT COALESCE(MAX(seq) + 1, 0) FROM events WHERE job_id = ?");
    GAPS_RETURN_IF_ERROR(next.prepared());
    next.bind(1, event.job_id());
    const int rc = next.step();
    GAPS_RETURN_IF_ERROR(next.done(rc));
    event.set_sequence(next.integer(0));
  }
  Statement s(db_, "INSERT INTO events (job_id, seq, event) VALUES (?, ?, ?)");
  GAPS_RETURN_IF_ERROR(s.prepared());
  s.bind(1, event.job_id());
  s.bind(2, event.sequence());
  s.bind_blob(3, event.SerializeAsString());
  return s.done(s.step());
}

absl::StatusOr<std::vector<v1::JobEvent>> JobStore::events(const std::string& job_id, int64_t from_sequence) {
  std::lock_guard<std::mutex> lock(mutex_);
  Statement s(db_, "SELECT event FROM events WHERE job_id = ? AND seq >= ? ORDER BY seq");
  GAPS_RETURN_IF_ERROR(s.prepared());
  s.bind(1, job_id);
  s.bind(2, from_sequence);
  std::vector<v1::JobEvent> out;
  int rc;
  while ((rc = s.step()) == SQLITE_ROW) {
    GAPS_ASSIGN_OR_RETURN(v1::JobEvent e, parse<v1::JobEvent>(s.blob(0), "job event"));
    out.push_back(std::move(e));
  }
  GAPS_RETURN_IF_ERROR(s.done(rc));
  return out;
}

absl::Status JobStore::set_artifacts(const std::string& job_id, const std::vector<Artifact>& artifacts) {
  std::lock_guard<std::mutex> lock(mutex_);
  return transaction([&] { return set_artifacts_locked(job_id, artifacts); });
}

absl::Status JobStore::set_artifacts_locked(const std::string& job_id, const std::vector<Artifact>& artifacts) {
  Statement clear(db_, "DELETE FROM artifacts WHERE job_id = ?");
  GAPS_RETURN_IF_ERROR(clear.prepared());
  clear.bind(1, job_id);
  GAPS_RETURN_IF_ERROR(clear.done(clear.step()));
  for (const auto& a : artifacts) {
    Statement s(db_, "INSERT INTO artifacts (job_id, path, size) VALUES (?, ?, ?)");
    GAPS_RETURN_IF_ERROR(s.prepared());
    s.bind(1, job_id);
    s.bind(2, a.path);
    s.bind(3, a.size);
    GAPS_RETURN_IF_ERROR(s.done(s.step()));
  }
  return absl::OkStatus();
}

absl::Status JobStore::end_job(const v1::JobStatus& status, const std::vector<Artifact>& artifacts,
                               v1::JobEvent& event) {
  std::lock_guard<std::mutex> lock(mutex_);
  return transaction([&]() -> absl::Status {
    GAPS_RETURN_IF_ERROR(set_artifacts_locked(status.job_id(), artifacts));
    GAPS_RETURN_IF_ERROR(update_locked(status));
    return append_event_locked(event);
  });
}

absl::StatusOr<std::vector<JobStore::Artifact>> JobStore::artifacts(const std::string& job_id) {
  std::lock_guard<std::mutex> lock(mutex_);
  Statement s(db_, "SELECT path, size FROM artifacts WHERE job_id = ? ORDER BY path");
  GAPS_RETURN_IF_ERROR(s.prepared());
  s.bind(1, job_id);
  std::vector<Artifact> out;
  int rc;
  while ((rc = s.step()) == SQLITE_ROW) out.push_back({s.text(0), s.integer(1)});
  GAPS_RETURN_IF_ERROR(s.done(rc));
  return out;
}

}  // namespace gaps

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

// A prepared statement that finalises itself.
class Statement {
 public:
  Statement(sqlite3* db, const char* sql) : db_(db) { rc_ = sqlite3_prepare_v2(db, sql, -1, &stmt_, nullptr); }
  ~Statement() { sqlite3_finalize(stmt_); }
  absl::Status prepared() const {
    return rc_ == SQLITE_OK ? absl::OkStatus() : absl::InternalError(absl::StrCat("SQLite: ", sqlite3_errmsg(db_)));
  }
  void bind(int i, const std::string& text) { sqlite3_bind_text(stmt_, i, text.data(), text.size(), SQLITE_TRANSIENT); }
  void bind_blob(int i, const std::string& bytes) {
    sqlite3_bind_blob(stmt_, i, bytes.data(), static_cast<int>(bytes.size()), SQLITE_TRANSIENT);
  }
  void bind(int i, int64_t v) { sqlite3_bind_int64(stmt_, i, v); }
  void bind(int i, double v) { sqlite3_bind_double(stmt_, i, v); }
  // SQLITE_ROW, SQLITE_DONE or an error code.
  int step() { return sqlite3_step(stmt_); }
  absl::Status done(int rc) const {
    return rc == SQLITE_DONE || rc == SQLITE_ROW ? absl::OkStatus()
                                                 : absl::InternalError(absl::StrCat("SQLite: ", sqlite3_errmsg(db_)));
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
  sqlite3* db_;
  sqlite3_stmt* stmt_ = nullptr;
  int rc_;
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
  if (sqlite3_exec(db_, sql.c_str(), nullptr, nullptr, &error) != SQLITE_OK) {
    const std::string message = error ? error : "unknown error";
    sqlite3_free(error);
    return absl::InternalError(absl::StrCat("SQLite: ", message));
  }
  return absl::OkStatus();
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
  Statement next(db_, "SELECT COALESCE(MAX(seq) + 1, 0) FROM events WHERE job_id = ?");
  GAPS_RETURN_IF_ERROR(next.prepared());
  next.bind(1, event.job_id());
  const int rc = next.step();
  GAPS_RETURN_IF_ERROR(next.done(rc));
  event.set_sequence(next.integer(0));
  Statement s(db_, "INSERT INTO events (job_id, seq, event) VALUES (?, ?, ?)");
  GAPS_RETURN_IF_ERROR(s.prepared());
  s.bind(1, event.job_id());
  s.bind(2, event.sequence());
  s.bind_blob(3, event.SerializeAsString());
  GAPS_RETURN_IF_ERROR(s.done(s.step()));
  return event.sequence();
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
  GAPS_RETURN_IF_ERROR(exec("BEGIN"));
  absl::Status status = [&]() -> absl::Status {
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
  }();
  GAPS_RETURN_IF_ERROR(exec(status.ok() ? "COMMIT" : "ROLLBACK"));
  return status;
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

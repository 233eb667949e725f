// SqlDriver over an SQLite file: WAL journal, a busy timeout, $N parameters read as ?N.
#include <sqlite3.h>

#include <regex>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "absl/strings/str_replace.h"
#include "common/status_macros.h"
#include "server/sql_driver.h"

namespace gaps {
namespace {

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

std::string sqlite_dialect(absl::string_view sql) {
  static const std::regex parameter(R"(\$([0-9]+))");
  const std::string words = absl::StrReplaceAll(
      sql, {{"{BLOB}", "BLOB"},
            {"{REAL}", "REAL"},
            {"{NOW}", "((julianday('now') - 2440587.5) * 86400.0)"},
            // One writer at a time (every transaction begins IMMEDIATE): rows need no locks of their own.
            {"{SKIP_LOCKED}", ""},
            {"{LOCK}", ""}});
  return std::regex_replace(words, parameter, "?$1");
}

class SqliteDriver final : public SqlDriver {
 public:
  SqliteDriver(sqlite3* db, std::string file) : db_(db), file_(std::move(file)) {}
  ~SqliteDriver() override { sqlite3_close(db_); }

  std::string describe() const override { return "SQLite " + file_; }

  absl::StatusOr<SqlResult> run(absl::string_view sql, const std::vector<SqlParam>& params) override {
    const std::string text = sqlite_dialect(sql);
    if (params.empty() && text.find(';') != std::string::npos) return exec(text);
    sqlite3_stmt* stmt = nullptr;
    int rc = sqlite3_prepare_v2(db_, text.c_str(), -1, &stmt, nullptr);
    std::unique_ptr<sqlite3_stmt, decltype(&sqlite3_finalize)> owned(stmt, &sqlite3_finalize);
    for (size_t i = 0; rc == SQLITE_OK && i < params.size(); ++i) rc = bind(stmt, static_cast<int>(i) + 1, params[i]);
    if (rc != SQLITE_OK) return sqlite_error(rc, sqlite3_errmsg(db_));
    SqlResult result;
    while ((rc = sqlite3_step(stmt)) == SQLITE_ROW) result.rows.push_back(row(stmt));
    if (rc != SQLITE_DONE) return sqlite_error(rc, sqlite3_errmsg(db_));
    result.affected = sqlite3_stmt_readonly(stmt) ? 0 : sqlite3_changes(db_);
    return result;
  }

  absl::Status begin() override { return exec("BEGIN IMMEDIATE").status(); }

  absl::Status rollback() override {
    // A failed COMMIT can leave the transaction open: every later write would join it and be lost with it.
    if (sqlite3_get_autocommit(db_) != 0) return absl::OkStatus();
    return exec("ROLLBACK").status();
  }

 private:
  absl::StatusOr<SqlResult> exec(const std::string& sql) {
    char* error = nullptr;
    const int rc = sqlite3_exec(db_, sql.c_str(), nullptr, nullptr, &error);
    if (rc == SQLITE_OK) return SqlResult{};
    const std::string message = error ? error : sqlite3_errstr(rc);
    sqlite3_free(error);
    return sqlite_error(rc, message);
  }

  static int bind(sqlite3_stmt* stmt, int i, const SqlParam& p) {
    switch (p.kind) {
      case SqlParam::Kind::kText:
        return sqlite3_bind_text64(stmt, i, p.text.data(), p.text.size(), SQLITE_TRANSIENT, SQLITE_UTF8);
      case SqlParam::Kind::kBlob:
        return sqlite3_bind_blob64(stmt, i, p.text.data(), p.text.size(), SQLITE_TRANSIENT);
      case SqlParam::Kind::kInt:
        return sqlite3_bind_int64(stmt, i, p.integer);
      case SqlParam::Kind::kReal:
        return sqlite3_bind_double(stmt, i, p.real);
      case SqlParam::Kind::kNull:
        return sqlite3_bind_null(stmt, i);
    }
    return SQLITE_MISUSE;
  }

  static std::vector<std::optional<std::string>> row(sqlite3_stmt* stmt) {
    std::vector<std::optional<std::string>> values;
    for (int c = 0; c < sqlite3_column_count(stmt); ++c) {
      switch (sqlite3_column_type(stmt, c)) {
        case SQLITE_NULL:
          values.emplace_back();
          break;
        case SQLITE_INTEGER:
          values.emplace_back(std::to_string(sqlite3_column_int64(stmt, c)));
          break;
        case SQLITE_FLOAT:
          values.emplace_back(absl::StrFormat("%.17g", sqlite3_column_double(stmt, c)));
          break;
        default: {  // text and blobs, as bytes
          const void* p = sqlite3_column_blob(stmt, c);
          values.emplace_back(p ? std::string(static_cast<const char*>(p), sqlite3_column_bytes(stmt, c)) : "");
        }
      }
    }
    return values;
  }

  sqlite3* db_;
  std::string file_;
};

}  // namespace

absl::StatusOr<std::unique_ptr<SqlDriver>> open_sqlite(const std::string& file) {
  sqlite3* db = nullptr;
  if (sqlite3_open(file.c_str(), &db) != SQLITE_OK) {
    const std::string message = db ? sqlite3_errmsg(db) : "out of memory";
    sqlite3_close(db);
    return absl::UnavailableError(absl::StrCat(file, ": cannot open job database (", message, ")"));
  }
  auto driver = std::make_unique<SqliteDriver>(db, file);
  // SQLite falls back to read-only for a file it may not write; every job would then fail at its first
  // write instead of the trainer at its start.
  if (sqlite3_db_readonly(db, "main") == 1)
    return absl::PermissionDeniedError(absl::StrCat(file, ": the job database is read-only"));
  sqlite3_busy_timeout(db, 5000);
  // WAL with synchronous=NORMAL: no fsync per event; a killed process loses nothing, a power loss at most
  // the last transactions, and the database stays consistent either way.
  GAPS_RETURN_IF_ERROR(
      driver->run("PRAGMA journal_mode=WAL; PRAGMA synchronous=NORMAL; PRAGMA foreign_keys=ON;", {}).status());
  return std::unique_ptr<SqlDriver>(std::move(driver));
}

}  // namespace gaps

#pragma once
// The SQL databases the job store runs on, behind one small interface: SQLite (embedded, one trainer) and
// PostgreSQL (shared by trainer replicas). Statements are written once, with $1..$N parameters and a few
// dialect words in braces ({BLOB}, {REAL}, {NOW}, {SKIP_LOCKED}, {LOCK}) that each driver fills in.
// Errors say what a caller can do: UNAVAILABLE (busy, locked, connection lost: try again),
// RESOURCE_EXHAUSTED (disk full), PERMISSION_DENIED (read-only), INTERNAL (anything else), each with the
// database's own message.
#include <cstdint>
#include <memory>
#include <optional>
#include <string>
#include <vector>

#include "absl/status/statusor.h"
#include "absl/strings/string_view.h"

namespace gaps {

// A statement parameter: text, raw bytes (BLOB/BYTEA), an integer, a real or NULL.
struct SqlParam {
  enum class Kind { kText, kBlob, kInt, kReal, kNull };
  Kind kind = Kind::kNull;
  std::string text;  // text or bytes
  int64_t integer = 0;
  double real = 0;

  static SqlParam Text(std::string v) { return {Kind::kText, std::move(v)}; }
  static SqlParam Blob(std::string v) { return {Kind::kBlob, std::move(v)}; }
  static SqlParam Int(int64_t v) { return {Kind::kInt, "", v}; }
  static SqlParam Real(double v) { return {Kind::kReal, "", 0, v}; }
  static SqlParam Null() { return {}; }
};

// Rows of a statement: every value as bytes (numbers in decimal text, blobs raw), nullopt for NULL.
struct SqlResult {
  std::vector<std::vector<std::optional<std::string>>> rows;
  int64_t affected = 0;  // rows changed by an INSERT, UPDATE or DELETE
};

class SqlDriver {
 public:
  virtual ~SqlDriver() = default;
  // "SQLite FILE" or "PostgreSQL host=... dbname=..." (no password): for logs and errors.
  virtual std::string describe() const = 0;
  // Runs one statement (or, without parameters, several separated by semicolons).
  virtual absl::StatusOr<SqlResult> run(absl::string_view sql, const std::vector<SqlParam>& params = {}) = 0;
  // Starts a transaction that takes the write lock at once (SQLite: BEGIN IMMEDIATE), so two writers
  // never both read, then both fail to upgrade.
  virtual absl::Status begin() = 0;
  // After a failure inside a transaction: rolls back if one is open.
  virtual absl::Status rollback() = 0;
};

// SQLite file (created if missing); PERMISSION_DENIED for a database this process may not write.
absl::StatusOr<std::unique_ptr<SqlDriver>> open_sqlite(const std::string& file);
// A libpq connection string or URI ("postgresql://user:password@host:5432/db").
absl::StatusOr<std::unique_ptr<SqlDriver>> open_postgres(const std::string& conninfo);

// The int64 in a result value (decimal text); 0 for NULL.
int64_t sql_int(const std::optional<std::string>& value);
double sql_real(const std::optional<std::string>& value);

}  // namespace gaps

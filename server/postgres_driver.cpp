// SqlDriver over one libpq connection. Parameters travel as text except blobs (binary BYTEA); results come
// back as text, BYTEA unescaped. A lost connection is reset once per failing call, which reports
// UNAVAILABLE so that the caller tries again.
#include <libpq-fe.h>

#include <cstdlib>

#include "absl/strings/ascii.h"
#include "absl/strings/match.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "absl/strings/str_replace.h"
#include "common/status_macros.h"
#include "server/sql_driver.h"

namespace gaps {
namespace {

constexpr Oid kByteaOid = 17;

std::string postgres_dialect(absl::string_view sql) {
  return absl::StrReplaceAll(sql, {{"{BLOB}", "BYTEA"},
                                   {"{REAL}", "DOUBLE PRECISION"},
                                   {"{NOW}", "extract(epoch from clock_timestamp())::DOUBLE PRECISION"},
                                   {"{SKIP_LOCKED}", "FOR UPDATE SKIP LOCKED"},
                                   {"{LOCK}", "FOR UPDATE"}});
}

// SQLSTATE classes (PostgreSQL appendix A) mapped to what a caller can do.
absl::StatusCode code_for(absl::string_view sqlstate) {
  if (absl::StartsWith(sqlstate, "53")) return absl::StatusCode::kResourceExhausted;  // disk full, out of memory
  if (sqlstate == "25006" || sqlstate == "42501") return absl::StatusCode::kPermissionDenied;
  if (absl::StartsWith(sqlstate, "08") || absl::StartsWith(sqlstate, "57") || sqlstate == "40001" ||
      sqlstate == "40P01" || sqlstate == "55P03")
    return absl::StatusCode::kUnavailable;  // connection, shutdown, serialization, deadlock, lock timeout
  return absl::StatusCode::kInternal;
}

class PostgresDriver final : public SqlDriver {
 public:
  explicit PostgresDriver(PGconn* conn) : conn_(conn) {
    // Notices ("relation already exists, skipping") are not errors; the store reports what matters.
    PQsetNoticeProcessor(
        conn_, [](void*, const char*) {}, nullptr);
  }
  ~PostgresDriver() override { PQfinish(conn_); }

  std::string describe() const override {
    return absl::StrCat("PostgreSQL host=", PQhost(conn_), " port=", PQport(conn_), " dbname=", PQdb(conn_),
                        " user=", PQuser(conn_));
  }

  absl::StatusOr<SqlResult> run(absl::string_view sql, const std::vector<SqlParam>& params) override {
    const std::string text = postgres_dialect(sql);
    std::vector<std::string> numbers(params.size());
    std::vector<const char*> values(params.size());
    std::vector<int> lengths(params.size()), formats(params.size());
    std::vector<Oid> types(params.size());
    for (size_t i = 0; i < params.size(); ++i) {
      const SqlParam& p = params[i];
      switch (p.kind) {
        case SqlParam::Kind::kText:
        case SqlParam::Kind::kBlob:
          values[i] = p.text.data();
          lengths[i] = static_cast<int>(p.text.size());
          formats[i] = p.kind == SqlParam::Kind::kBlob ? 1 : 0;
          types[i] = p.kind == SqlParam::Kind::kBlob ? kByteaOid : 0;
          break;
        case SqlParam::Kind::kInt:
          numbers[i] = std::to_string(p.integer);
          values[i] = numbers[i].c_str();
          break;
        case SqlParam::Kind::kReal:
          numbers[i] = absl::StrFormat("%.17g", p.real);
          values[i] = numbers[i].c_str();
          break;
        case SqlParam::Kind::kNull:
          values[i] = nullptr;
          break;
      }
    }
    PGresult* raw = params.empty() ? PQexec(conn_, text.c_str())
                                   : PQexecParams(conn_, text.c_str(), static_cast<int>(params.size()), types.data(),
                                                  values.data(), lengths.data(), formats.data(), 0);
    std::unique_ptr<PGresult, decltype(&PQclear)> result(raw, &PQclear);
    const ExecStatusType status = result ? PQresultStatus(result.get()) : PGRES_FATAL_ERROR;
    if (status != PGRES_COMMAND_OK && status != PGRES_TUPLES_OK) return failure(result.get());
    return rows(result.get());
  }

  absl::Status begin() override { return run("BEGIN", {}).status(); }

  absl::Status rollback() override {
    if (PQtransactionStatus(conn_) == PQTRANS_IDLE) return absl::OkStatus();
    return run("ROLLBACK", {}).status();
  }

 private:
  absl::Status failure(const PGresult* result) {
    const char* sqlstate = result ? PQresultErrorField(result, PG_DIAG_SQLSTATE) : nullptr;
    std::string message = result ? PQresultErrorMessage(result) : "";
    if (message.empty()) message = PQerrorMessage(conn_);
    absl::StripTrailingAsciiWhitespace(&message);
    absl::StatusCode code = sqlstate ? code_for(sqlstate) : absl::StatusCode::kUnavailable;
    if (PQstatus(conn_) != CONNECTION_OK) {
      code = absl::StatusCode::kUnavailable;
      PQreset(conn_);  // the next call gets a fresh connection, or fails the same way
    }
    return absl::Status(code, absl::StrCat("job store: ", message));
  }

  static SqlResult rows(const PGresult* result) {
    SqlResult out;
    const int n = PQntuples(result), columns = PQnfields(result);
    for (int r = 0; r < n; ++r) {
      std::vector<std::optional<std::string>> row;
      for (int c = 0; c < columns; ++c) {
        if (PQgetisnull(result, r, c)) {
          row.emplace_back();
        } else if (PQftype(result, c) == kByteaOid) {
          size_t length = 0;
          unsigned char* bytes =
              PQunescapeBytea(reinterpret_cast<const unsigned char*>(PQgetvalue(result, r, c)), &length);
          row.emplace_back(std::string(reinterpret_cast<const char*>(bytes), length));
          PQfreemem(bytes);
        } else {
          row.emplace_back(std::string(PQgetvalue(result, r, c), PQgetlength(result, r, c)));
        }
      }
      out.rows.push_back(std::move(row));
    }
    const char* affected = PQcmdTuples(const_cast<PGresult*>(result));
    out.affected = affected && *affected ? std::atoll(affected) : 0;
    return out;
  }

  PGconn* conn_;
};

}  // namespace

absl::StatusOr<std::unique_ptr<SqlDriver>> open_postgres(const std::string& conninfo) {
  PGconn* conn = PQconnectdb(conninfo.c_str());
  if (conn == nullptr) return absl::ResourceExhaustedError("job store: libpq could not allocate a connection");
  if (PQstatus(conn) != CONNECTION_OK) {
    std::string message = PQerrorMessage(conn);
    absl::StripTrailingAsciiWhitespace(&message);
    PQfinish(conn);
    // The connection string may hold a password: the error names the server libpq reports instead.
    return absl::UnavailableError(absl::StrCat("job store: cannot connect to PostgreSQL: ", message));
  }
  return std::unique_ptr<SqlDriver>(new PostgresDriver(conn));
}

}  // namespace gaps

#pragma once
// Propagation helpers for absl::Status / absl::StatusOr across module boundaries.
#include "absl/status/status.h"
#include "absl/status/statusor.h"

#define GAPS_CONCAT_INNER(a, b) a##b
#define GAPS_CONCAT(a, b) GAPS_CONCAT_INNER(a, b)

#define GAPS_RETURN_IF_ERROR(expr)               \
  do {                                           \
    ::absl::Status gaps_status_ = (expr);        \
    if (!gaps_status_.ok()) return gaps_status_; \
  } while (0)

#define GAPS_ASSIGN_OR_RETURN_IMPL(var, lhs, expr) \
  auto var = (expr);                               \
  if (!var.ok()) return var.status();              \
  lhs = std::move(*var)

#define GAPS_ASSIGN_OR_RETURN(lhs, expr) GAPS_ASSIGN_OR_RETURN_IMPL(GAPS_CONCAT(gaps_statusor_, __LINE__), lhs, expr)

#include "common/error_kind.h"

#include <string>

#include "absl/strings/cord.h"

namespace gaps {
namespace {

constexpr char kPayloadUrl[] = "type.gaps/ErrorKind";

}  // namespace

absl::Status with_error_kind(absl::Status status, ErrorKind kind) {
  if (!status.ok()) status.SetPayload(kPayloadUrl, absl::Cord(std::to_string(static_cast<int>(kind))));
  return status;
}

ErrorKind error_kind(const absl::Status& status) {
  if (const auto payload = status.GetPayload(kPayloadUrl)) {
    const std::string text(*payload);
    for (ErrorKind kind : {ErrorKind::kUsage, ErrorKind::kDiverged, ErrorKind::kInputData, ErrorKind::kUnreachable})
      if (text == std::to_string(static_cast<int>(kind))) return kind;
  }
  return absl::IsUnavailable(status) ? ErrorKind::kUnreachable : ErrorKind::kOther;
}

int exit_code(const absl::Status& status) { return status.ok() ? 0 : static_cast<int>(error_kind(status)); }

absl::Status usage_error(absl::string_view message) {
  return with_error_kind(absl::InvalidArgumentError(message), ErrorKind::kUsage);
}

absl::Status input_data_error(absl::Status status) { return with_error_kind(std::move(status), ErrorKind::kInputData); }

}  // namespace gaps

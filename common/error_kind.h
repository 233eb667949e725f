#pragma once
// What kind of mistake an error is, carried by its absl::Status from where that is known (the scene loader
// knows a file is unreadable, the command line that a flag is wrong) to the program's exit status. The exit
// codes are the table in docs/usage.md ("Conventions and exit statuses") and in every program's --help.
#include "absl/status/status.h"

namespace gaps {

enum class ErrorKind : int {
  kOther = 1,        // anything else, internal errors included
  kUsage = 2,        // a flag, argument or option value (the message names it)
  kDiverged = 3,     // the training became non-finite (metrics.json says "diverged")
  kInputData = 4,    // the scene, an image, a point cloud or an options file cannot be read or is invalid
  kUnreachable = 5,  // a service (gaps-trainer, a diffusion worker) does not answer
};

// `status` tagged with `kind` (an OK status stays OK).
absl::Status with_error_kind(absl::Status status, ErrorKind kind);
// The kind `status` was tagged with; untagged: kUnreachable for UNAVAILABLE, otherwise kOther.
ErrorKind error_kind(const absl::Status& status);
// The exit code of a command that ends with `status`: 0 when OK, otherwise its kind's code.
int exit_code(const absl::Status& status);

// Shorthands: an INVALID_ARGUMENT usage error, and an error of the input data keeping its status code.
absl::Status usage_error(absl::string_view message);
absl::Status input_data_error(absl::Status status);

}  // namespace gaps

#pragma once
// `gaps view` (serve the web viewer of a run, a PLY or a .splat on this machine) and `gaps export` (a run's
// model as a .splat file or a self-contained viewer page). Both return the exit code (common/error_kind.h).
#include "common/cli/command_line.h"

namespace gaps::client {

// --host, --port.
cli::FlagGroup view_flags();
// --format (with -o/--out, the file written).
cli::FlagGroup export_flags();

int run_view(const cli::CommandLine& line);
int run_export(const cli::CommandLine& line);

}  // namespace gaps::client

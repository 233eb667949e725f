#pragma once
// The commands of `gaps` that run in this process (through gs_trainer/pipeline.h): train, init, demo, options.
// Each checks its flags, scene and output folder before any expensive work and returns the exit code
// (common/error_kind.h; 128 + the signal for a `gaps train` stopped by SIGINT/SIGTERM after saving the run).
#include "common/cli/command_line.h"

namespace gaps::client {

int run_train(const cli::CommandLine& line);
int run_init(const cli::CommandLine& line);
int run_demo(const cli::CommandLine& line);
int print_options();

}  // namespace gaps::client

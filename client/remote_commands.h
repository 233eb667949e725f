#pragma once
// The remote subcommands of `gaps`: submit, watch, list, cancel, fetch (see client/README.md); `gaps render
// --job` (client/render_commands.h) connects through connect_trainer() too.
#include <string>

#include "absl/status/statusor.h"
#include "client/remote_client.h"
#include "common/cli/command_line.h"

namespace gaps::client {

// --trainer, --token-file and the --tls-* flags of every remote command.
cli::FlagGroup remote_flags();
// What only `gaps submit` takes besides the scene and run flags: --name, --watch, --quiet.
cli::FlagGroup submit_flags();

// A client of the trainer the flags name (--trainer, --token-file, --tls-*), once it answers: an unreachable
// one is an error tagged unreachable before anything expensive happens.
absl::StatusOr<TrainerClient> connect_trainer();

bool is_remote_command(const std::string& command);
// Runs a remote command whose flags `line` has parsed. Returns the process exit code.
int run_remote_command(const std::string& command, const cli::CommandLine& line);

}  // namespace gaps::client

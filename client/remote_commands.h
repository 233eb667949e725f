#pragma once
// The remote subcommands of `gaps`: submit, watch, list, cancel, fetch (see client/README.md).
#include <string>
#include <vector>

namespace gaps::client {

bool is_remote_command(const std::string& command);
// `args` are the positional arguments after the command name. Returns the process exit code.
int run_remote_command(const std::string& command, const std::vector<std::string>& args);

}  // namespace gaps::client

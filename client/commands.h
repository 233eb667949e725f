#pragma once
// The commands of `gaps`: what each takes (its flag groups, short forms, arguments) and says in --help.
#include <string>
#include <vector>

#include "common/cli/command_line.h"

namespace gaps::client {

std::vector<cli::CommandSpec> gaps_commands();
// `gaps --help`: the commands, one line each, the flag conventions and the exit codes.
std::string gaps_overview();

}  // namespace gaps::client

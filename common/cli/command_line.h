#pragma once
// The command-line conventions of gaps, gaps-trainer and gaps-worker, in one place. Flags are absl flags,
// defined where they are used; a command lists the ones it takes (CommandSpec) and parse_command_line reads
// its arguments against that list, so every program spells them alike:
//   --name=value or --name value; dashes and underscores alike (--data-dir, --data_dir);
//   booleans bare (--quiet), with a value (--report=false) or negated (--no-report);
//   the short forms a command declares (-r 8 for --resolution 8); -h/--help; --version; `--` ends the flags.
// A flag the command does not take is refused with the closest name ("did you mean --iterations?") or the
// sibling commands that take it; a stray argument is refused.
#include <functional>
#include <map>
#include <optional>
#include <set>
#include <string>
#include <vector>

#include "absl/status/statusor.h"

namespace gaps::cli {

struct FlagGroup {
  std::string title;
  std::vector<std::string> names;  // absl flag names (underscored), in the order --help lists them
};

struct CommandSpec {
  std::string name;      // as messages and --help name it: "gaps train", "gaps-trainer"
  std::string synopsis;  // the usage line(s)
  std::string summary;   // what the command does
  std::vector<FlagGroup> groups;
  std::map<std::string, std::string> short_names;  // "r" -> "resolution"
  // Positional arguments: at most this many, described as `positional_name` in messages.
  int max_positional = 0;
  std::string positional_name;
  std::string epilogue;  // printed after the flags (e.g. a pointer to exit_code_table())
  // Flags users try that the command has no need for, with why ("eval" -> "every 8th image is a test view"):
  // added to the refusal, so that the user learns what to do instead of guessing at a near name.
  std::map<std::string, std::string> unneeded_flags;
};

struct CommandLine {
  std::vector<std::string> positional;
  std::set<std::string> given;  // the flags given (absl names)
  bool help = false;
  bool version = false;
  bool has(const std::string& name) const { return given.count(name) > 0; }
};

// Reads `args` (what follows the program, or the program and its command) for `spec`, setting the absl
// flags given. `siblings`: the program's other commands, to say which of them takes a flag this one does
// not. Every error is a usage error (common/error_kind.h) whose message names the argument.
absl::StatusOr<CommandLine> parse_command_line(const std::vector<std::string>& args, const CommandSpec& spec,
                                               const std::vector<CommandSpec>& siblings = {});

// For a program without commands (gaps-trainer, gaps-worker): parses argv for `spec`. --help and --version
// print and give 0, a usage error prints "PROGRAM: message" and gives its exit code; nothing: go on.
std::optional<int> parse_program_command_line(int argc, char** argv, const CommandSpec& spec);

// --help: synopsis, summary, then every flag of every group with its default and meaning, then the epilogue.
std::string help_text(const CommandSpec& spec);
// --version: "PROGRAM VERSION (commit HASH)", the commit as of the build's configuration.
std::string version_text(const std::string& program);
// The exit codes every program uses (the table in docs/usage.md, "Conventions and exit statuses").
std::string exit_code_table();
// A flag as users type it: "init_ply" -> "--init-ply".
std::string display_name(const std::string& flag);
// The candidate closest to `word` when close enough to be a likely typo or an unambiguous prefix; "" if none.
std::string closest_match(const std::string& word, const std::vector<std::string>& candidates);

// main's body behind a last line of defence: an exception, from this thread or (through std::terminate) any
// other, becomes one line "PROGRAM: internal error: WHAT" and exit status 1 instead of an abort.
int run_main(const std::string& program, const std::function<int()>& body);

}  // namespace gaps::cli

// gaps: the command line. train, init, demo and options run in this process (client/local_commands.h), view
// and export too (client/view_commands.h), and render and eval (client/render_commands.h);
// submit, watch, list, cancel and fetch talk to a gaps-trainer service (client/remote_commands.h). Every
// command's flags are in client/commands.cpp; `gaps <command> --help` lists them.
#include <iostream>
#include <string>
#include <vector>

#include "client/commands.h"
#include "client/local_commands.h"
#include "client/remote_commands.h"
#include "client/render_commands.h"
#include "client/view_commands.h"
#include "common/cli/command_line.h"
#include "common/error_kind.h"

namespace {

int usage(const std::string& message) {
  std::cerr << "gaps: " << message << "\n";
  return static_cast<int>(gaps::ErrorKind::kUsage);
}

// `gaps help exit-codes` (the table every command's --help points to) or `gaps help COMMAND`.
int help_topic(const std::vector<std::string>& args) {
  if (args.size() == 2 && args[1] == "exit-codes") {
    std::cout << gaps::cli::exit_code_table();
    return 0;
  }
  for (const auto& spec : gaps::client::gaps_commands())
    if (args.size() == 2 && spec.name == "gaps " + args[1]) {
      std::cout << gaps::cli::help_text(spec);
      return 0;
    }
  return usage("gaps help takes one topic: exit-codes or a command (gaps --help lists them)");
}

int run(int argc, char** argv) {
  namespace client = gaps::client;
  const std::vector<std::string> args(argv + 1, argv + argc);
  const std::string first = args.empty() ? "" : args[0];
  if (first == "help" && args.size() > 1) return help_topic(args);
  if (first == "--help" || first == "-h" || first == "help") {
    std::cout << client::gaps_overview();
    return 0;
  }
  if (first == "--version") {
    std::cout << gaps::cli::version_text("gaps");
    return 0;
  }
  if (args.empty()) {
    std::cerr << client::gaps_overview();
    return static_cast<int>(gaps::ErrorKind::kUsage);
  }
  const std::vector<gaps::cli::CommandSpec> commands = client::gaps_commands();
  std::vector<std::string> names;
  const gaps::cli::CommandSpec* spec = nullptr;
  for (const auto& c : commands) {
    names.push_back(c.name.substr(c.name.find(' ') + 1));
    if (names.back() == first) spec = &c;
  }
  if (spec == nullptr) {
    if (first[0] == '-') return usage("the command comes first: gaps <command> [flags] (gaps --help lists them)");
    const std::string close = gaps::cli::closest_match(first, names);
    return usage("unknown command '" + first + "'" + (close.empty() ? "" : "; did you mean " + close + "?") +
                 " (gaps --help lists them)");
  }
  const auto line = gaps::cli::parse_command_line({args.begin() + 1, args.end()}, *spec, commands);
  if (!line.ok()) {
    std::cerr << spec->name << ": " << line.status().message() << "\n";
    return gaps::exit_code(line.status());
  }
  if (line->help) {
    std::cout << gaps::cli::help_text(*spec);
    return 0;
  }
  if (line->version) {
    std::cout << gaps::cli::version_text("gaps");
    return 0;
  }
  if (first == "train") return client::run_train(*line);
  if (first == "init") return client::run_init(*line);
  if (first == "demo") return client::run_demo(*line);
  if (first == "options") return client::print_options();
  if (first == "view") return client::run_view(*line);
  if (first == "export") return client::run_export(*line);
  if (first == "render") return client::run_render(*line);
  if (first == "eval") return client::run_eval(*line);
  return client::run_remote_command(first, *line);
}

}  // namespace

int main(int argc, char** argv) {
  return gaps::cli::run_main("gaps", [&] { return run(argc, argv); });
}

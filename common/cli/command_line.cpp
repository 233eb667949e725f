#include "common/cli/command_line.h"

#include <algorithm>
#include <cstdio>
#include <cstdlib>
#include <exception>
#include <optional>
#include <stdexcept>

#include "absl/flags/commandlineflag.h"
#include "absl/flags/reflection.h"
#include "absl/strings/match.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_join.h"
#include "absl/strings/str_split.h"
#include "common/error_kind.h"

#include "gaps_commit.h"  // generated at build time: GAPS_COMMIT

namespace gaps::cli {
namespace {

std::string flag_name(absl::string_view typed) {
  std::string name(typed);
  std::replace(name.begin(), name.end(), '-', '_');
  return name;
}

std::vector<std::string> accepted_names(const CommandSpec& spec) {
  std::vector<std::string> names;
  for (const FlagGroup& group : spec.groups) names.insert(names.end(), group.names.begin(), group.names.end());
  return names;
}

bool takes(const CommandSpec& spec, const std::string& name) {
  const std::vector<std::string> names = accepted_names(spec);
  return std::find(names.begin(), names.end(), name) != names.end();
}

absl::CommandLineFlag& registered(const std::string& name) {
  absl::CommandLineFlag* flag = absl::FindCommandLineFlag(name);
  // A command listing a flag nobody defined is a programming error, not a user's.
  if (flag == nullptr) throw std::logic_error(absl::StrCat("flag --", name, " is listed but not defined"));
  return *flag;
}

// Restricted Damerau-Levenshtein distance (an adjacent swap counts as one edit).
size_t edit_distance(const std::string& a, const std::string& b) {
  std::vector<std::vector<size_t>> d(a.size() + 1, std::vector<size_t>(b.size() + 1));
  for (size_t i = 0; i <= a.size(); ++i) d[i][0] = i;
  for (size_t j = 0; j <= b.size(); ++j) d[0][j] = j;
  for (size_t i = 1; i <= a.size(); ++i) {
    for (size_t j = 1; j <= b.size(); ++j) {
      d[i][j] = std::min({d[i - 1][j] + 1, d[i][j - 1] + 1, d[i - 1][j - 1] + (a[i - 1] == b[j - 1] ? 0 : 1)});
      if (i > 1 && j > 1 && a[i - 1] == b[j - 2] && a[i - 2] == b[j - 1])
        d[i][j] = std::min(d[i][j], d[i - 2][j - 2] + 1);
    }
  }
  return d[a.size()][b.size()];
}

// "unknown flag --iteratons; did you mean --iterations?", or which sibling commands take the flag.
absl::Status unknown_flag(const std::string& typed, const std::string& name, const CommandSpec& spec,
                          const std::vector<CommandSpec>& siblings) {
  std::vector<std::string> takers;
  for (const CommandSpec& other : siblings)
    if (other.name != spec.name && takes(other, name)) takers.push_back(other.name);
  if (!takers.empty())
    return usage_error(absl::StrCat(typed, " is not a flag of ", spec.name, "; ", absl::StrJoin(takers, ", "),
                                    takers.size() == 1 ? " takes it" : " take it"));
  // A near name would send the user after a flag that does something else; the note says what happens anyway.
  if (const auto unneeded = spec.unneeded_flags.find(name); unneeded != spec.unneeded_flags.end())
    return usage_error(absl::StrCat(typed, " is not a flag of ", spec.name, " and none is needed: ", unneeded->second));
  const std::string suggestion = closest_match(name, accepted_names(spec));
  return usage_error(absl::StrCat(
      "unknown flag ", typed, suggestion.empty() ? "" : absl::StrCat("; did you mean ", display_name(suggestion), "?"),
      " (", spec.name, " --help lists its flags)"));
}

absl::Status stray_argument(const std::string& arg, const CommandSpec& spec) {
  if (spec.max_positional == 0)
    return usage_error(
        absl::StrCat("unexpected argument '", arg, "': ", spec.name, " takes only flags (--name value)"));
  return usage_error(absl::StrCat("unexpected argument '", arg, "': ", spec.name, " takes at most ",
                                  spec.max_positional, " (", spec.positional_name, ")"));
}

// Sets one flag from its typed form (`typed`: as given, for messages). `inline_value` is what followed '='.
absl::Status set_flag(const std::string& typed, const std::string& name, const std::optional<std::string>& inline_value,
                      const std::vector<std::string>& args, size_t& i, CommandLine& line) {
  absl::CommandLineFlag& flag = registered(name);
  std::string value;
  if (inline_value) {
    value = *inline_value;
  } else if (flag.IsOfType<bool>()) {
    value = "true";
  } else if (i + 1 < args.size()) {
    value = args[++i];
  } else {
    return usage_error(absl::StrCat(typed, " needs a value"));
  }
  std::string error;
  if (!flag.ParseFrom(value, &error))
    return usage_error(absl::StrCat(typed, " ", value, ": not a valid ", flag.IsOfType<bool>() ? "true/false" : "value",
                                    " (", error, ")"));
  line.given.insert(name);
  return absl::OkStatus();
}

// --tryfromenv=a,b (Abseil's spelling): each named flag of the command takes the value of the environment
// variable FLAGS_<name> when that is set, so that a deployment can lay settings over a command line (compose
// merges environments key by key, but appends to command lines).
absl::Status flags_from_environment(const std::string& list, const CommandSpec& spec, CommandLine& line) {
  for (absl::string_view item : absl::StrSplit(list, ',', absl::SkipEmpty())) {
    const std::string name = flag_name(item);
    if (!takes(spec, name))
      return usage_error(absl::StrCat("--tryfromenv: ", spec.name, " has no flag ", display_name(name)));
    const char* value = std::getenv(("FLAGS_" + name).c_str());
    if (value == nullptr) continue;
    std::string error;
    if (!registered(name).ParseFrom(value, &error))
      return usage_error(
          absl::StrCat("FLAGS_", name, "=", value, ": not a valid value for ", display_name(name), " (", error, ")"));
    line.given.insert(name);
  }
  return absl::OkStatus();
}

// --no-report / --noreport: the name of the boolean flag it negates, or "".
std::string negated_bool(const std::string& name, const CommandSpec& spec) {
  for (const char* prefix : {"no_", "no"}) {
    if (!absl::StartsWith(name, prefix)) continue;
    const std::string base = name.substr(std::string(prefix).size());
    if (takes(spec, base) && registered(base).IsOfType<bool>()) return base;
  }
  return "";
}

// Words wrapped to `width` columns, starting at `column`; continuation lines are indented by `indent`.
std::string wrap(const std::string& text, size_t indent, size_t column, size_t width = 118) {
  std::string out;
  bool first = true;
  for (absl::string_view word : absl::StrSplit(text, ' ', absl::SkipEmpty())) {
    if (!first && column + 1 + word.size() > width) {
      absl::StrAppend(&out, "\n", std::string(indent, ' '));
      column = indent;
    } else if (!first) {
      out += ' ';
      ++column;
    }
    absl::StrAppend(&out, word);
    column += word.size();
    first = false;
  }
  return out;
}

std::string flag_help_line(const std::string& name, const CommandSpec& spec) {
  const absl::CommandLineFlag& flag = registered(name);
  std::string left = "  ";
  for (const auto& [short_name, long_name] : spec.short_names)
    if (long_name == name) absl::StrAppend(&left, "-", short_name, ", ");
  absl::StrAppend(&left, display_name(name));
  const std::string default_value = flag.DefaultValue();
  if (flag.IsOfType<bool>()) {
    if (default_value == "true") absl::StrAppend(&left, " (default true; --no-", name, ")");
  } else if (!default_value.empty()) {
    absl::StrAppend(&left, "=", default_value);
  }
  constexpr size_t kHelpColumn = 32;
  if (left.size() + 1 >= kHelpColumn)
    return absl::StrCat(left, "\n", std::string(kHelpColumn, ' '), wrap(flag.Help(), kHelpColumn, kHelpColumn), "\n");
  return absl::StrCat(left, std::string(kHelpColumn - left.size(), ' '), wrap(flag.Help(), kHelpColumn, kHelpColumn),
                      "\n");
}

std::string g_program = "gaps";

std::string first_line(const std::string& text) { return text.substr(0, text.find('\n')); }

[[noreturn]] void on_terminate() {
  std::string what = "terminated";
  if (const std::exception_ptr error = std::current_exception()) {
    try {
      std::rethrow_exception(error);
    } catch (const std::exception& e) {
      what = first_line(e.what());
    } catch (...) {
      what = "unknown exception";
    }
  }
  std::fprintf(stderr, "%s: internal error: %s\n", g_program.c_str(), what.c_str());
  std::_Exit(static_cast<int>(ErrorKind::kOther));
}

}  // namespace

std::string display_name(const std::string& flag) {
  std::string name = flag;
  std::replace(name.begin(), name.end(), '_', '-');
  return "--" + name;
}

std::string closest_match(const std::string& word, const std::vector<std::string>& candidates) {
  std::string best;
  size_t best_distance = std::string::npos;
  std::vector<std::string> extensions;
  for (const std::string& c : candidates) {
    if (word.size() >= 3 && absl::StartsWith(c, word)) extensions.push_back(c);
    const size_t d = edit_distance(word, c);
    if (d < best_distance) best_distance = d, best = c;
  }
  if (extensions.size() == 1) return extensions[0];
  const size_t allowed = word.size() <= 4 ? 1 : word.size() <= 8 ? 2 : 3;
  return best_distance <= allowed ? best : "";
}

absl::StatusOr<CommandLine> parse_command_line(const std::vector<std::string>& args, const CommandSpec& spec,
                                               const std::vector<CommandSpec>& siblings) {
  CommandLine line;
  bool flags_ended = false;
  for (size_t i = 0; i < args.size(); ++i) {
    const std::string& arg = args[i];
    if (flags_ended || arg.size() < 2 || arg[0] != '-') {
      if (line.positional.size() == static_cast<size_t>(spec.max_positional)) return stray_argument(arg, spec);
      line.positional.push_back(arg);
      continue;
    }
    if (arg == "--") {
      flags_ended = true;
      continue;
    }
    if (arg == "-h" || arg == "--help" || arg == "-help") {
      line.help = true;
      continue;
    }
    if (arg == "--version") {
      line.version = true;
      continue;
    }
    const bool is_long = absl::StartsWith(arg, "--");
    const std::string body = arg.substr(is_long ? 2 : 1);
    const size_t equals = body.find('=');
    const std::string typed = arg.substr(0, (is_long ? 2 : 1) + std::min(equals, body.size()));
    std::optional<std::string> inline_value;
    if (equals != std::string::npos) inline_value = body.substr(equals + 1);
    std::string name = flag_name(body.substr(0, equals));
    if (!is_long) {
      const auto short_name = spec.short_names.find(body.substr(0, equals));
      if (short_name == spec.short_names.end())
        return usage_error(absl::StrCat("unknown flag ", typed, " (", spec.name, " --help lists its flags)"));
      name = short_name->second;
    }
    if (name == "tryfromenv" && is_long) {
      std::string list;
      if (inline_value) {
        list = *inline_value;
      } else if (i + 1 < args.size()) {
        list = args[++i];
      } else {
        return usage_error("--tryfromenv needs a list of flag names");
      }
      if (absl::Status st = flags_from_environment(list, spec, line); !st.ok()) return st;
      continue;
    }
    if (!takes(spec, name)) {
      const std::string negated = inline_value ? "" : negated_bool(name, spec);
      if (negated.empty()) return unknown_flag(typed, name, spec, siblings);
      std::string error;
      if (!registered(negated).ParseFrom("false", &error)) return usage_error(absl::StrCat(typed, ": ", error));
      line.given.insert(negated);
      continue;
    }
    if (absl::Status st = set_flag(typed, name, inline_value, args, i, line); !st.ok()) return st;
  }
  return line;
}

std::optional<int> parse_program_command_line(int argc, char** argv, const CommandSpec& spec) {
  const absl::StatusOr<CommandLine> line = parse_command_line({argv + 1, argv + argc}, spec);
  if (!line.ok()) {
    std::fprintf(stderr, "%s: %s\n", spec.name.c_str(), std::string(line.status().message()).c_str());
    return exit_code(line.status());
  }
  if (line->help) {
    std::fputs(help_text(spec).c_str(), stdout);
    return 0;
  }
  if (line->version) {
    std::fputs(version_text(spec.name).c_str(), stdout);
    return 0;
  }
  return std::nullopt;
}

std::string help_text(const CommandSpec& spec) {
  std::string out = absl::StrCat("usage: ", spec.synopsis, "\n\n", spec.summary, "\n");
  for (const FlagGroup& group : spec.groups) {
    if (group.names.empty()) continue;
    absl::StrAppend(&out, "\n", group.title, ":\n");
    for (const std::string& name : group.names) out += flag_help_line(name, spec);
  }
  absl::StrAppend(&out, "\n",
                  "Flags take dashes or underscores (--init-ply, --init_ply), --name=value or --name value.\n");
  if (!spec.epilogue.empty()) absl::StrAppend(&out, "\n", spec.epilogue);
  return out;
}

std::string version_text(const std::string& program) {
  return absl::StrCat(program, " ", GAPS_VERSION, " (commit ", GAPS_COMMIT, ")\n");
}

std::string exit_code_table() {
  return "exit status:\n"
         "  0    success\n"
         "  1    any other failure (the message says what)\n"
         "  2    usage: a flag, argument or option value is wrong (the message names it)\n"
         "  3    the training diverged (non-finite loss or parameters; metrics.json says \"diverged\")\n"
         "  4    input data: the scene, an image, a point cloud or a file named by a flag is unreadable or invalid\n"
         "  5    a service (gaps-trainer, diffusion worker) cannot be reached\n"
         "  130  gaps train stopped by SIGINT (143: SIGTERM) after saving the run; gaps train --resume OUT goes on\n";
}

int run_main(const std::string& program, const std::function<int()>& body) {
  g_program = program;
  std::set_terminate(on_terminate);
  try {
    return body();
  } catch (const std::exception& e) {
    std::fprintf(stderr, "%s: internal error: %s\n", program.c_str(), first_line(e.what()).c_str());
  } catch (...) {
    std::fprintf(stderr, "%s: internal error: unknown exception\n", program.c_str());
  }
  return static_cast<int>(ErrorKind::kOther);
}

}  // namespace gaps::cli

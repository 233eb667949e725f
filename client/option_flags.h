#pragma once
// One command-line flag per training and GAPS option, generated from the option tables (common/option_table.h),
// shared by `gaps train`, `init`, `demo` and `submit`. A flag overrides the config file only when it is given
// on the command line; options_from_files_and_flags says which source won for every overridden field.
#include <string>
#include <vector>

#include <nlohmann/json.hpp>
#include "absl/status/statusor.h"
#include "common/option_table.h"

namespace gaps::client {

// A flag's text as given. Unset flags keep `given` false and show the option's default in --help.
struct OptionFlag {
  std::string text;
  bool given = false;
};
bool AbslParseFlag(absl::string_view text, OptionFlag* flag, std::string* error);
std::string AbslUnparseFlag(const OptionFlag& flag);

// The training ("training") and GAPS ("gaps") options of a run: each config file (may be empty: none) with the
// flags given on the command line laid over it, as JSON objects of the config files' shape (only the keys the
// file or a flag set). `notes` gets one line per option where a flag replaced the file's value.
struct GivenOptions {
  nlohmann::json training = nlohmann::json::object();
  nlohmann::json gaps = nlohmann::json::object();
  std::vector<std::string> notes;
};
absl::StatusOr<GivenOptions> options_from_files_and_flags(const std::string& training_file,
                                                          const std::string& gaps_file);

// The flags' names, in table order: the training options and the GAPS options.
std::vector<std::string> training_option_flag_names();
std::vector<std::string> gaps_option_flag_names();

// How `gaps options` names an option's type and range to users: "integer", "number", "true/false", "text",
// "list of numbers"; "[1, 1000000]", ">= 0" (a bound at the type's limit, or a stand-in as large as 1e9, is no
// bound a user meets), integers written as integers; "" for no range.
std::string option_type_words(const std::string& cpp_type);
std::string option_range_words(const OptionInfo& option);

}  // namespace gaps::client

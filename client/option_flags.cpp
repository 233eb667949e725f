#include "client/option_flags.h"

#include <cmath>
#include <cstdint>
#include <limits>

#include "absl/flags/flag.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "common/cli/command_line.h"
#include "common/error_kind.h"
#include "common/io_util.h"
#include "common/status_macros.h"
#include "gs_trainer/gaps/config.h"
#include "gs_trainer/train/train_config.h"

namespace gaps::client {

bool AbslParseFlag(absl::string_view text, OptionFlag* flag, std::string*) {
  flag->text = std::string(text);
  flag->given = true;
  return true;
}

std::string AbslUnparseFlag(const OptionFlag& flag) { return flag.text; }

namespace {

// The default as --help shows it: strings bare, everything else as JSON.
OptionFlag default_flag(const nlohmann::json& value) {
  return {value.is_string() ? value.get<std::string>() : value.dump(), false};
}

}  // namespace
}  // namespace gaps::client

#define GAPS_DEFINE_OPTION_FLAG(type, name, def, lo, hi, help) \
  ABSL_FLAG(gaps::client::OptionFlag, name, gaps::client::default_flag(nlohmann::json(type(def))), help);
GAPS_TRAIN_CONFIG_OPTIONS(GAPS_DEFINE_OPTION_FLAG)
GAPS_GAPS_CONFIG_OPTIONS(GAPS_DEFINE_OPTION_FLAG)
#undef GAPS_DEFINE_OPTION_FLAG

namespace gaps::client {
namespace {

struct FlagEntry {
  const char* name;
  const absl::Flag<OptionFlag>* flag;
};

#define GAPS_FLAG_ENTRY(type, name, def, lo, hi, help) {#name, &FLAGS_##name},
const FlagEntry kTrainingFlags[] = {GAPS_TRAIN_CONFIG_OPTIONS(GAPS_FLAG_ENTRY)};
const FlagEntry kGapsFlags[] = {GAPS_GAPS_CONFIG_OPTIONS(GAPS_FLAG_ENTRY)};
#undef GAPS_FLAG_ENTRY

std::vector<std::string> names_of(const FlagEntry* begin, const FlagEntry* end) {
  std::vector<std::string> names;
  for (const FlagEntry* e = begin; e != end; ++e) names.push_back(e->name);
  return names;
}

// Unreadable or malformed files are input data errors; their values are checked with the flags'.
absl::StatusOr<nlohmann::json> read_options_file(const std::string& path) {
  if (path.empty()) return nlohmann::json::object();
  absl::StatusOr<std::string> text = read_file_bytes(path, "options file");
  if (!text.ok()) return input_data_error(text.status());
  nlohmann::json j = nlohmann::json::parse(*text, nullptr, /*allow_exceptions=*/false);
  if (j.is_discarded()) return input_data_error(absl::InvalidArgumentError(absl::StrCat(path, ": invalid JSON")));
  if (!j.is_object())
    return input_data_error(absl::InvalidArgumentError(absl::StrCat(path, ": options must be a JSON object")));
  return j;
}

// A flag's text as the JSON value of its option: a string option takes the text as it is; the others parse it
// as JSON, a list also as comma-separated numbers without brackets.
absl::StatusOr<nlohmann::json> flag_value(const std::string& name, const std::string& text,
                                          const nlohmann::json& default_value) {
  if (default_value.is_string()) return nlohmann::json(text);
  std::string json_text = text;
  if (default_value.is_array() && (json_text.empty() || json_text.front() != '[')) json_text = "[" + text + "]";
  nlohmann::json j = nlohmann::json::parse(json_text, nullptr, /*allow_exceptions=*/false);
  if (j.is_discarded()) return usage_error(absl::StrCat(cli::display_name(name), " ", text, ": not a valid value"));
  return j;
}

// Lays the given flags of one section over `options`, noting each key that was in the file.
absl::Status apply_flags(const FlagEntry* begin, const FlagEntry* end, const nlohmann::json& defaults,
                         const std::string& file, nlohmann::json& options, std::vector<std::string>& notes) {
  for (const FlagEntry* e = begin; e != end; ++e) {
    const OptionFlag flag = absl::GetFlag(*e->flag);
    if (!flag.given) continue;
    GAPS_ASSIGN_OR_RETURN(nlohmann::json value, flag_value(e->name, flag.text, defaults.at(e->name)));
    if (options.contains(e->name) && options[e->name] != value)
      notes.push_back(absl::StrCat(e->name, " = ", value.dump(), " from the command line, over ",
                                   options[e->name].dump(), " in ", file));
    options[e->name] = std::move(value);
  }
  return absl::OkStatus();
}

}  // namespace

std::vector<std::string> training_option_flag_names() {
  return names_of(std::begin(kTrainingFlags), std::end(kTrainingFlags));
}
std::vector<std::string> gaps_option_flag_names() { return names_of(std::begin(kGapsFlags), std::end(kGapsFlags)); }

absl::StatusOr<GivenOptions> options_from_files_and_flags(const std::string& training_file,
                                                          const std::string& gaps_file) {
  GivenOptions given;
  GAPS_ASSIGN_OR_RETURN(given.training, read_options_file(training_file));
  GAPS_ASSIGN_OR_RETURN(given.gaps, read_options_file(gaps_file));
  GAPS_RETURN_IF_ERROR(apply_flags(std::begin(kTrainingFlags), std::end(kTrainingFlags), TrainConfig{}, training_file,
                                   given.training, given.notes));
  GAPS_RETURN_IF_ERROR(
      apply_flags(std::begin(kGapsFlags), std::end(kGapsFlags), GapsConfig{}, gaps_file, given.gaps, given.notes));
  return given;
}

namespace {

bool is_integer_type(const std::string& cpp_type) {
  return cpp_type == "int" || cpp_type == "int64_t" || cpp_type == "uint64_t";
}

// The largest value of an option's C++ type (int's for int, and so on); infinity for the others.
double type_max(const std::string& cpp_type) {
  if (cpp_type == "int") return std::numeric_limits<int>::max();
  if (cpp_type == "int64_t") return static_cast<double>(std::numeric_limits<int64_t>::max());
  if (cpp_type == "uint64_t") return static_cast<double>(std::numeric_limits<uint64_t>::max());
  return std::numeric_limits<double>::infinity();
}

// The tables write "no limit" as the type's limit or as a round 1e9 and more; neither is a limit users meet.
constexpr double kStandInForNoLimit = 1e9;

bool bounds(double value, const std::string& cpp_type) {
  return std::isfinite(value) && std::abs(value) < kStandInForNoLimit && std::abs(value) < type_max(cpp_type);
}

// Whole values as integers (1000000, not 1e+06), whatever the type.
std::string number_words(double value, const std::string& cpp_type) {
  if (is_integer_type(cpp_type) || value == std::floor(value)) return absl::StrFormat("%.0f", value);
  return absl::StrFormat("%g", value);
}

}  // namespace

std::string option_type_words(const std::string& cpp_type) {
  if (is_integer_type(cpp_type)) return "integer";
  if (cpp_type == "double") return "number";
  if (cpp_type == "bool") return "true/false";
  if (cpp_type == "std::string") return "text";
  if (cpp_type == "std::vector<double>") return "list of numbers";
  return cpp_type;
}

std::string option_range_words(const OptionInfo& o) {
  if (o.type == "bool" || o.type == "std::string") return "";
  const bool has_min = bounds(o.min, o.type), has_max = bounds(o.max, o.type);
  if (has_min && has_max) return absl::StrCat("[", number_words(o.min, o.type), ", ", number_words(o.max, o.type), "]");
  if (has_min) return absl::StrCat(">= ", number_words(o.min, o.type));
  if (has_max) return absl::StrCat("<= ", number_words(o.max, o.type));
  return "";
}

}  // namespace gaps::client

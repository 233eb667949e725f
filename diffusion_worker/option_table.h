#pragma once
// A backend's JSON options as one table: each entry's key, the field it sets, the values it accepts and a
// one-line help. Parsing, the errors (an unknown key lists the known ones; a wrong type or value names the
// key and what it accepts) and the check of options built in code all follow from the table, so a new
// option is one line of it.
#include <algorithm>
#include <cstdint>
#include <functional>
#include <limits>
#include <optional>
#include <string>
#include <type_traits>
#include <utility>
#include <vector>

#include <nlohmann/json.hpp>
#include "absl/status/status.h"

namespace gaps {

// The numbers an option accepts: finite, within optional bounds, odd where asked (integers).
struct NumberRange {
  std::optional<double> min, max;
  bool min_inclusive = true, max_inclusive = true, odd = false;

  bool contains(double value) const;
  // e.g. "an integer >= 1", "an odd integer >= 1", "a number in [0, 1)".
  std::string describe(bool integer) const;
};
NumberRange at_least(double min);      // [min, inf)
NumberRange above(double min);         // (min, inf)
NumberRange odd_at_least(double min);  // odd, [min, inf)
// brackets: "[]", "[)", "(]" or "()", the interval's ends as written.
NumberRange between(double min, double max, const char* brackets);

template <typename Options>
struct Option {
  std::string name;
  std::string accepts;  // what a valid value is, as errors say it: "a string", "an integer >= 1"
  std::string help;     // one line; errors about the option end with it
  // Sets the field from a JSON value; false (the field untouched) when the value is not one `accepts` allows.
  std::function<bool(const nlohmann::json&, Options&)> set;
  std::function<nlohmann::json(const Options&)> get;  // the field's value
};

// access: a data member pointer (&Options::steps) or a generic lambda returning a reference to the field
// ([](auto& o) -> auto& { return o.depth_control.min_alpha; }), usable on const and non-const Options.
template <typename Options, typename Access>
Option<Options> string_option(std::string name, Access access, std::string help, std::vector<std::string> choices = {});
template <typename Options, typename Access>
Option<Options> bool_option(std::string name, Access access, std::string help);
template <typename Options, typename Access>
Option<Options> integer_option(std::string name, Access access, NumberRange range, std::string help);
template <typename Options, typename Access>
Option<Options> number_option(std::string name, Access access, NumberRange range, std::string help);

// backend names the options in errors: "<backend> option 'key' = <value>: must be <accepts> (<help>)".
template <typename Options>
class OptionTable {
 public:
  OptionTable(std::string backend, std::vector<Option<Options>> options)
      : backend_(std::move(backend)), options_(std::move(options)) {}

  // Sets the field of every key of a JSON object; an unknown key, a wrong type or a value out of range is
  // an error naming the key.
  absl::Status apply(const nlohmann::json& object, Options& options) const;
  // Every field's value is one its option accepts (for options built in code rather than parsed).
  absl::Status validate(const Options& options) const;

  const std::vector<Option<Options>>& options() const { return options_; }
  std::vector<std::string> names() const;
  const Option<Options>* find(const std::string& name) const;

 private:
  std::string backend_;
  std::vector<Option<Options>> options_;
};

namespace option_table_internal {

absl::Status unknown_option(const std::string& backend, const std::string& key, const std::vector<std::string>& known);
absl::Status bad_value(const std::string& backend, const std::string& key, const std::string& accepts,
                       const std::string& help, const nlohmann::json& value);
std::string describe_choices(const std::vector<std::string>& choices);
// The integer a JSON value holds, if it holds one that fits int64_t.
std::optional<int64_t> json_integer(const nlohmann::json& value);

template <typename Options, typename Access>
std::function<nlohmann::json(const Options&)> getter(Access access) {
  return [access](const Options& o) { return nlohmann::json(std::invoke(access, o)); };
}

}  // namespace option_table_internal

template <typename Options, typename Access>
Option<Options> string_option(std::string name, Access access, std::string help, std::vector<std::string> choices) {
  std::string accepts = choices.empty() ? "a string" : option_table_internal::describe_choices(choices);
  auto set = [access, choices](const nlohmann::json& v, Options& o) {
    if (!v.is_string()) return false;
    const auto& s = v.get_ref<const std::string&>();
    if (!choices.empty() && std::find(choices.begin(), choices.end(), s) == choices.end()) return false;
    std::invoke(access, o) = s;
    return true;
  };
  return {std::move(name), std::move(accepts), std::move(help), set, option_table_internal::getter<Options>(access)};
}

template <typename Options, typename Access>
Option<Options> bool_option(std::string name, Access access, std::string help) {
  auto set = [access](const nlohmann::json& v, Options& o) {
    if (!v.is_boolean()) return false;
    std::invoke(access, o) = v.get<bool>();
    return true;
  };
  return {std::move(name), "true or false", std::move(help), set, option_table_internal::getter<Options>(access)};
}

template <typename Options, typename Access>
Option<Options> integer_option(std::string name, Access access, NumberRange range, std::string help) {
  auto set = [access, range](const nlohmann::json& v, Options& o) {
    using Field = std::decay_t<decltype(std::invoke(access, o))>;
    static_assert(std::is_integral_v<Field>, "integer_option needs an integer field");
    const std::optional<int64_t> value = option_table_internal::json_integer(v);
    if (!value || !range.contains(static_cast<double>(*value)) || *value < std::numeric_limits<Field>::min() ||
        *value > std::numeric_limits<Field>::max()) {
      return false;
    }
    std::invoke(access, o) = static_cast<Field>(*value);
    return true;
  };
  return {std::move(name), range.describe(/*integer=*/true), std::move(help), set,
          option_table_internal::getter<Options>(access)};
}

template <typename Options, typename Access>
Option<Options> number_option(std::string name, Access access, NumberRange range, std::string help) {
  auto set = [access, range](const nlohmann::json& v, Options& o) {
    if (!v.is_number() || !range.contains(v.get<double>())) return false;
    std::invoke(access, o) = v.get<double>();
    return true;
  };
  return {std::move(name), range.describe(/*integer=*/false), std::move(help), set,
          option_table_internal::getter<Options>(access)};
}

template <typename Options>
absl::Status OptionTable<Options>::apply(const nlohmann::json& object, Options& options) const {
  for (auto it = object.begin(); it != object.end(); ++it) {
    const Option<Options>* option = find(it.key());
    if (option == nullptr) return option_table_internal::unknown_option(backend_, it.key(), names());
    if (!option->set(it.value(), options))
      return option_table_internal::bad_value(backend_, option->name, option->accepts, option->help, it.value());
  }
  return absl::OkStatus();
}

template <typename Options>
absl::Status OptionTable<Options>::validate(const Options& options) const {
  for (const Option<Options>& option : options_) {
    Options scratch = options;
    const nlohmann::json value = option.get(options);
    if (!option.set(value, scratch))
      return option_table_internal::bad_value(backend_, option.name, option.accepts, option.help, value);
  }
  return absl::OkStatus();
}

template <typename Options>
std::vector<std::string> OptionTable<Options>::names() const {
  std::vector<std::string> names;
  for (const Option<Options>& option : options_) names.push_back(option.name);
  return names;
}

template <typename Options>
const Option<Options>* OptionTable<Options>::find(const std::string& name) const {
  for (const Option<Options>& option : options_)
    if (option.name == name) return &option;
  return nullptr;
}

}  // namespace gaps

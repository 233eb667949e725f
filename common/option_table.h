#pragma once
// Option structs (TrainConfig, GapsConfig) are described once, by an X-macro list with one entry per field:
//   X(type, name, default, min, max, "help")
// and everything else follows from that list, so that adding a field in one place is enough:
//   the struct's members        GAPS_DECLARE_OPTION
//   JSON write and read         GAPS_WRITE_OPTION, GAPS_READ_OPTION (unknown keys and wrong types are errors)
//   range checks                GAPS_CHECK_OPTION (min/max apply to numbers and to each element of a list)
//   descriptions                GAPS_DESCRIBE_OPTION (`gaps options`, docs/options.md, the flags' help)
//   command-line flags          client/option_flags.h
// The gaps.v1 hyperparameter messages carry fields of the same names; tests/options_test.cpp fails when one is
// missing or has another type.
#include <cmath>
#include <cstdint>
#include <limits>
#include <string>
#include <type_traits>
#include <vector>

#include <absl/status/status.h>
#include <absl/strings/str_cat.h>
#include <nlohmann/json.hpp>

// `type name = default;`
#define GAPS_DECLARE_OPTION(type, name, def, lo, hi, help) type name = def;
// With `j` the json and `c` the struct in scope.
#define GAPS_WRITE_OPTION(type, name, def, lo, hi, help) j[#name] = c.name;
// Inside the callback of read_options (key, value and c in scope).
#define GAPS_READ_OPTION(type, name, def, lo, hi, help) \
  if (key == #name) {                                   \
    ::gaps::read_option(value, #name, &c.name);         \
    return true;                                        \
  }
// Inside a function returning absl::Status, with `c` the struct in scope.
#define GAPS_CHECK_OPTION(type, name, def, lo, hi, help) \
  if (absl::Status s = ::gaps::check_option_range(#name, c.name, lo, hi); !s.ok()) return s;
// With `out` a std::vector<OptionInfo> and `section` a string in scope.
#define GAPS_DESCRIBE_OPTION(type, name, def, lo, hi, help) \
  out.push_back({section, #name, #type, nlohmann::json(type(def)), lo, hi, help});

namespace gaps {

inline constexpr double kUnbounded = std::numeric_limits<double>::infinity();

// One option as `gaps options` and the documentation show it.
struct OptionInfo {
  std::string section;  // "training" or "gaps": the config file and proto message it belongs to
  std::string name;
  std::string type;
  nlohmann::json default_value;
  double min = -kUnbounded;
  double max = kUnbounded;
  std::string help;
};

namespace option_internal {

[[noreturn]] inline void fail(const std::string& name, const std::string& what) {
  throw nlohmann::json::type_error::create(302, "option '" + name + "' " + what, nullptr);
}

}  // namespace option_internal

// Reads one option's JSON value, requiring the field's own type: an integer field takes integers that fit it
// (1e40 or 2.5 are errors, not silently converted), a list takes an array of numbers.
template <typename T>
void read_option(const nlohmann::json& value, const std::string& name, T* field) {
  using option_internal::fail;
  if constexpr (std::is_same_v<T, bool>) {
    if (!value.is_boolean()) fail(name, "must be true or false");
    *field = value.get<bool>();
  } else if constexpr (std::is_integral_v<T>) {
    if (!value.is_number_integer()) fail(name, "must be an integer");
    if (value.is_number_unsigned()) {
      const uint64_t v = value.get<uint64_t>();
      if (v > static_cast<uint64_t>(std::numeric_limits<T>::max())) fail(name, "is too large");
      *field = static_cast<T>(v);
    } else {
      const int64_t v = value.get<int64_t>();
      if ((std::is_unsigned_v<T> && v < 0) ||
          (std::is_signed_v<T> && (v < std::numeric_limits<T>::min() || v > std::numeric_limits<T>::max())))
        fail(name, "is out of the range of its type");
      *field = static_cast<T>(v);
    }
  } else if constexpr (std::is_floating_point_v<T>) {
    if (!value.is_number()) fail(name, "must be a number");
    *field = value.get<T>();
  } else if constexpr (std::is_same_v<T, std::string>) {
    if (!value.is_string()) fail(name, "must be a string");
    *field = value.get<std::string>();
  } else {
    static_assert(std::is_same_v<T, std::vector<double>>, "option type without a reader");
    if (!value.is_array()) fail(name, "must be a list of numbers");
    field->clear();
    for (const auto& x : value) {
      if (!x.is_number()) fail(name, "must be a list of numbers");
      field->push_back(x.get<double>());
    }
  }
}

// OK when a number lies in [lo, hi] (NaN never does), or every element of a list does; strings and booleans
// have no range.
template <typename T>
absl::Status check_option_range(const std::string& name, const T& value, double lo, double hi) {
  if constexpr (std::is_arithmetic_v<T> && !std::is_same_v<T, bool>) {
    const double v = static_cast<double>(value);
    if (!(v >= lo && v <= hi))
      return absl::InvalidArgumentError(absl::StrCat("option '", name, "' = ", v, " is outside [", lo, ", ", hi, "]"));
  } else if constexpr (std::is_same_v<T, std::vector<double>>) {
    for (double v : value)
      if (!(v >= lo && v <= hi))
        return absl::InvalidArgumentError(
            absl::StrCat("option '", name, "' has an element ", v, " outside [", lo, ", ", hi, "]"));
  }
  return absl::OkStatus();
}

// Calls read(key, value) for every entry of j; read returns false for a key it does not know, which throws
// nlohmann's other_error 501 naming the key as an unknown `what` option.
template <typename Read>
void read_options(const nlohmann::json& j, const std::string& what, Read read) {
  if (!j.is_object()) throw nlohmann::json::type_error::create(302, what + " options must be a JSON object", &j);
  for (auto it = j.begin(); it != j.end(); ++it) {
    if (!read(it.key(), it.value()))
      throw nlohmann::json::other_error::create(501, "unknown " + what + " option '" + it.key() + "'", &j);
  }
}

// An exception's message without nlohmann's "[json.exception.type_error.302] " prefix.
inline std::string json_error_message(const std::exception& e) {
  const std::string what = e.what();
  if (what.rfind("[json.exception.", 0) == 0) {
    const size_t end = what.find("] ");
    if (end != std::string::npos) return what.substr(end + 2);
  }
  return what;
}

}  // namespace gaps

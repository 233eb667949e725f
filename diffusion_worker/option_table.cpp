#include "diffusion_worker/option_table.h"

#include <algorithm>
#include <cstdint>
#include <cstring>
#include <limits>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_join.h"

namespace gaps {

bool NumberRange::contains(double value) const {
  if (!std::isfinite(value)) return false;
  if (min && (min_inclusive ? value < *min : value <= *min)) return false;
  if (max && (max_inclusive ? value > *max : value >= *max)) return false;
  return !odd || std::fmod(value, 2.0) != 0.0;
}

std::string NumberRange::describe(bool integer) const {
  std::string text = odd ? "an odd integer" : integer ? "an integer" : "a number";
  if (min && max) {
    return absl::StrCat(text, " in ", min_inclusive ? "[" : "(", *min, ", ", *max, max_inclusive ? "]" : ")");
  }
  if (min) return absl::StrCat(text, min_inclusive ? " >= " : " > ", *min);
  if (max) return absl::StrCat(text, max_inclusive ? " <= " : " < ", *max);
  return text;
}

NumberRange at_least(double min) { return NumberRange{min, std::nullopt}; }

NumberRange above(double min) {
  NumberRange range = at_least(min);
  range.min_inclusive = false;
  return range;
}

NumberRange odd_at_least(double min) {
  NumberRange range = at_least(min);
  range.odd = true;
  return range;
}

NumberRange between(double min, double max, const char* brackets) {
  NumberRange range{min, max};
  range.min_inclusive = brackets[0] == '[';
  range.max_inclusive = std::strlen(brackets) > 1 && brackets[1] == ']';
  return range;
}

namespace option_table_internal {
namespace {

size_t edit_distance(const std::string& a, const std::string& b) {
  std::vector<size_t> row(b.size() + 1);
  for (size_t j = 0; j <= b.size(); ++j) row[j] = j;
  for (size_t i = 1; i <= a.size(); ++i) {
    size_t diagonal = row[0];
    row[0] = i;
    for (size_t j = 1; j <= b.size(); ++j) {
      const size_t substitute = diagonal + (a[i - 1] != b[j - 1] ? 1 : 0);
      diagonal = row[j];
      row[j] = std::min({row[j] + 1, row[j - 1] + 1, substitute});
    }
  }
  return row[b.size()];
}

// The known name a mistyped key most likely meant: within a few edits (a third of its length, at least
// 2), or the only name containing it; "" when none is close.
std::string nearest_name(const std::string& key, const std::vector<std::string>& known) {
  std::string best;
  size_t best_distance = std::max<size_t>(2, key.size() / 3) + 1;
  for (const std::string& name : known) {
    const size_t d = edit_distance(key, name);
    if (d < best_distance) best = name, best_distance = d;
  }
  if (!best.empty() || key.size() < 4) return best;
  std::vector<std::string> containing;
  for (const std::string& name : known)
    if (name.find(key) != std::string::npos) containing.push_back(name);
  return containing.size() == 1 ? containing[0] : "";
}

}  // namespace

absl::Status unknown_option(const std::string& backend, const std::string& key, const std::vector<std::string>& known) {
  const std::string nearest = nearest_name(key, known);
  return absl::InvalidArgumentError(
      absl::StrCat("unknown ", backend, " option '", key, "'",
                   nearest.empty() ? "" : absl::StrCat(" (did you mean '", nearest, "'?)"),
                   "; known: ", absl::StrJoin(known, ", ")));
}

absl::Status bad_value(const std::string& backend, const std::string& key, const std::string& accepts,
                       const std::string& help, const nlohmann::json& value) {
  return absl::InvalidArgumentError(
      absl::StrCat(backend, " option '", key, "' = ", value.dump(), ": must be ", accepts, " (", help, ")"));
}

std::string describe_choices(const std::vector<std::string>& choices) {
  if (choices.size() == 1) return choices[0];
  const std::vector<std::string> head(choices.begin(), choices.end() - 1);
  return absl::StrCat(absl::StrJoin(head, ", "), " or ", choices.back());
}

std::optional<int64_t> json_integer(const nlohmann::json& value) {
  if (!value.is_number_integer()) return std::nullopt;
  if (value.is_number_unsigned() && value.get<uint64_t>() > static_cast<uint64_t>(std::numeric_limits<int64_t>::max()))
    return std::nullopt;
  return value.get<int64_t>();
}

}  // namespace option_table_internal
}  // namespace gaps

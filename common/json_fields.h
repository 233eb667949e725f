#pragma once
// JSON for the option structs (TrainConfig, GapsConfig) from one X-macro list of their fields, so that
// struct and JSON cannot drift apart and an unknown key is an error instead of a silently ignored typo.
//   to_json:   LIST(GAPS_WRITE_FIELD)            with `j` the json and `c` the struct in scope
//   from_json: read_fields(j, "training", [&](const std::string& key, const nlohmann::json& value) {
//                LIST(GAPS_READ_FIELD) return false; });
#include <string>

#include <nlohmann/json.hpp>

#define GAPS_WRITE_FIELD(f) j[#f] = c.f;
#define GAPS_READ_FIELD(f) \
  if (key == #f) {         \
    value.get_to(c.f);     \
    return true;           \
  }

namespace gaps {

// Calls read(key, value) for every entry of j; read returns false for a key it does not know, which
// throws nlohmann's other_error 501 naming the key as an unknown `what` option.
template <typename Read>
void read_fields(const nlohmann::json& j, const std::string& what, Read read) {
  for (auto it = j.begin(); it != j.end(); ++it) {
    if (!read(it.key(), it.value()))
      throw nlohmann::json::other_error::create(501, "unknown " + what + " option '" + it.key() + "'", &j);
  }
}

}  // namespace gaps

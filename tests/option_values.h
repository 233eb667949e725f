#pragma once
// Non-default values for every training and GAPS option, from the option tables, so that tests which carry
// options through files, flags, the proto and metrics.json cover every field, including ones added later.
#include <algorithm>
#include <map>
#include <string>

#include <nlohmann/json.hpp>
#include "gs_trainer/gaps/config.h"
#include "gs_trainer/train/train_config.h"

namespace gaps::test {

// A valid value other than the default: numbers move by about 10 % (or away from 0) inside their range,
// integers by one (two for odd-only ones), booleans flip; `overrides` (valid, non-default) win.
inline nlohmann::json non_default_value(const OptionInfo& o) {
  const nlohmann::json& d = o.default_value;
  if (d.is_boolean()) return !d.get<bool>();
  if (d.is_string()) return d.get<std::string>() == "cpu" ? "cuda" : "cpu";
  if (d.is_array()) {
    nlohmann::json out = nlohmann::json::array();
    for (const auto& x : d) out.push_back(x.get<double>() * 1.1);  // tiers stay nested and contain [0, 1]
    return out;
  }
  if (d.is_number_integer()) {
    const double step = o.name == "inpaint_dilation" ? 2 : 1;
    const double v = d.get<double>();
    return static_cast<int64_t>(v + step <= o.max ? v + step : v - step);
  }
  const double v = d.get<double>();
  double moved = v != 0 ? v * 1.1 : std::min(o.max, 1.0) * 0.05;
  if (moved > o.max || moved < o.min) moved = v * 0.9;
  return moved;
}

// Every option of `options` with a non-default value, as a config file would hold them.
inline nlohmann::json non_default_options(const std::vector<OptionInfo>& options,
                                          const nlohmann::json& overrides = nlohmann::json::object()) {
  nlohmann::json j = nlohmann::json::object();
  for (const OptionInfo& o : options) j[o.name] = non_default_value(o);
  j.update(overrides);
  return j;
}

}  // namespace gaps::test

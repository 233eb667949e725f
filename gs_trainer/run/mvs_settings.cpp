#include "gs_trainer/run/mvs_settings.h"

#include <type_traits>

#include <nlohmann/json.hpp>
#include "absl/strings/str_cat.h"

namespace gaps {
namespace {

// One table for both directions, so that a setting cannot be written without being read back. The names
// are the flags' (and gaps.v1.InitSettings's fields).
// Options: RunOptions or const RunOptions.
template <typename Options, typename Visit>
void visit_mvs_settings(Options& o, Visit&& visit) {
  visit("patchmatch_best_views", o.patchmatch.best_views);
  visit("patchmatch_max_cost", o.patchmatch.max_cost);
  visit("patchmatch_iterations", o.patchmatch.iterations);
  visit("patchmatch_max_image_side", o.patchmatch.max_image_side);
  visit("patchmatch_geometric_consistency", o.patchmatch.geometric_consistency);
  visit("fusion_min_views", o.fusion.min_views);
  visit("fusion_max_normal_error", o.fusion.max_normal_error_deg);
  visit("fusion_add_sparse", o.fusion.add_sparse_points);
  visit("sparse_max_image_side", o.sparse.max_image_side);
}

}  // namespace

nlohmann::json mvs_settings_json(const RunOptions& options) {
  nlohmann::json j = nlohmann::json::object();
  visit_mvs_settings(options, [&](const char* name, const auto& value) { j[name] = value; });
  return j;
}

nlohmann::json changed_mvs_settings(const RunOptions& options) {
  const nlohmann::json defaults = mvs_settings_json(RunOptions{}), settings = mvs_settings_json(options);
  nlohmann::json changed = nlohmann::json::object();
  for (const auto& [name, value] : settings.items())
    if (value != defaults.at(name)) changed[name] = value;
  return changed;
}

absl::Status read_mvs_settings(const nlohmann::json& settings, RunOptions& options) {
  if (!settings.is_object()) return absl::InvalidArgumentError("init settings: not a JSON object");
  const nlohmann::json known = mvs_settings_json(options);
  for (const auto& [name, value] : settings.items())
    if (!known.contains(name)) return absl::InvalidArgumentError(absl::StrCat("init settings: unknown '", name, "'"));
  absl::Status status;
  visit_mvs_settings(options, [&](const char* name, auto& value) {
    if (!status.ok() || !settings.contains(name)) return;
    try {
      value = settings[name].get<std::remove_reference_t<decltype(value)>>();
    } catch (const std::exception& e) {
      status = absl::InvalidArgumentError(absl::StrCat("init settings: ", name, ": ", e.what()));
    }
  });
  return status;
}

absl::Status validate_mvs_settings(const RunOptions& options) {
  if (absl::Status s = validate_patchmatch_options(options.patchmatch); !s.ok())
    return absl::InvalidArgumentError(absl::StrCat("PatchMatch: ", s.message()));
  if (absl::Status s = validate_fusion_options(options.fusion); !s.ok())
    return absl::InvalidArgumentError(absl::StrCat("fusion: ", s.message()));
  if (absl::Status s = validate_sparse_options(options.sparse); !s.ok())
    return absl::InvalidArgumentError(absl::StrCat("sparse: ", s.message()));
  return absl::OkStatus();
}

}  // namespace gaps

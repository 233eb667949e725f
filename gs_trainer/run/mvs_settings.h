#pragma once
// RunOptions' initialisation settings (PatchMatch, fusion, the sparse stage) as JSON: what metrics.json and a run
// folder's record keep, and what a submitted job carries.
#include <nlohmann/json_fwd.hpp>
#include "absl/status/status.h"
#include "gs_trainer/run/options.h"

namespace gaps {

// The initialisation settings a user may change (RunOptions::patchmatch, ::fusion without max_points) as one
// JSON object keyed by the flags' names ("patchmatch_best_views", ..., "fusion_max_normal_error"): what
// metrics.json and a run folder's record keep, and the fields of gaps.v1.InitSettings.
nlohmann::json mvs_settings_json(const RunOptions& options);
// The settings of mvs_settings_json that differ from the defaults.
nlohmann::json changed_mvs_settings(const RunOptions& options);
// Reads such an object into `options`; settings it lacks keep their values (a job that sets a few, records written
// before the settings existed). Errors name an unknown setting or one whose value has the wrong type; ranges are
// validate_mvs_settings's.
absl::Status read_mvs_settings(const nlohmann::json& settings, RunOptions& options);
// The range check of those settings: InvalidArgument prefixed "PatchMatch: " or "fusion: ".
absl::Status validate_mvs_settings(const RunOptions& options);

}  // namespace gaps

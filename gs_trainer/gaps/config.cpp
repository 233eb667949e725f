#include "gs_trainer/gaps/config.h"

#include <string>

#include <absl/strings/str_cat.h>
#include <nlohmann/json.hpp>

namespace gaps {

namespace {

absl::Status invalid(const std::string& what) { return absl::InvalidArgumentError("GAPS config: " + what); }

// Tier k must contain tier k-1 so that upgrades only add candidates, and tier 0 must contain the
// interpolation interval [0, 1] (eq:slerp samples along and beyond the baseline).
absl::Status validate_tiers(const GapsConfig& c) {
  if (c.tier_alpha_min.empty() || c.tier_alpha_min.size() != c.tier_alpha_max.size()) {
    return invalid("tier_alpha_min and tier_alpha_max must be non-empty and of equal length");
  }
  if (c.tier_alpha_min[0] > 0.0 || c.tier_alpha_max[0] < 1.0) return invalid("tier 0 must contain [0, 1]");
  for (size_t k = 1; k < c.tier_alpha_min.size(); ++k) {
    if (c.tier_alpha_min[k] > c.tier_alpha_min[k - 1] || c.tier_alpha_max[k] < c.tier_alpha_max[k - 1]) {
      return invalid(absl::StrCat("tier ", k, " does not contain tier ", k - 1));
    }
  }
  return absl::OkStatus();
}

}  // namespace

absl::Status validate_gaps_config(const GapsConfig& c) {
  GAPS_GAPS_CONFIG_OPTIONS(GAPS_CHECK_OPTION)
  if (absl::Status s = validate_tiers(c); !s.ok()) return s;
  if (c.strength_min > c.strength_max) return invalid("strength_min is above strength_max");
  const absl::Status inpaint = check_inpaint_settings(inpaint_settings(c));
  if (!inpaint.ok()) return invalid(std::string(inpaint.message()));
  return absl::OkStatus();
}

std::vector<OptionInfo> gaps_config_options() {
  std::vector<OptionInfo> out;
  const std::string section = "gaps";
  GAPS_GAPS_CONFIG_OPTIONS(GAPS_DESCRIBE_OPTION)
  return out;
}

int n_active_for(const GapsConfig& c, bool views_surround_scene) {
  if (c.n_active > 0) return c.n_active;
  return views_surround_scene ? kNActiveMip360 : kNActiveLlff;
}

int diffusion_phase_at(int iteration, int total_iterations, const GapsConfig& c) {
  if (iteration < c.warmup_iterations || iteration >= total_iterations) return -1;
  const int since = iteration - c.warmup_iterations;
  return since % c.phase_interval == 0 ? since / c.phase_interval : -1;
}

int num_diffusion_phases(int total_iterations, const GapsConfig& c) {
  if (total_iterations <= c.warmup_iterations) return 0;
  return (total_iterations - 1 - c.warmup_iterations) / c.phase_interval + 1;
}

// The first phase runs before iteration warmup_iterations (0-based; diffusion_phase_at), so the run needs one
// more than that.
int iterations_for_first_phase(const GapsConfig& c) { return c.warmup_iterations + 1; }

void to_json(nlohmann::json& j, const GapsConfig& c) { GAPS_GAPS_CONFIG_OPTIONS(GAPS_WRITE_OPTION) }

void from_json(const nlohmann::json& j, GapsConfig& c) {
  read_options(j, "GAPS", [&](const std::string& key, const nlohmann::json& value) {
    GAPS_GAPS_CONFIG_OPTIONS(GAPS_READ_OPTION)
    return false;
  });
  if (absl::Status s = validate_gaps_config(c); !s.ok()) {
    throw nlohmann::json::other_error::create(502, std::string(s.message()), &j);
  }
}

}  // namespace gaps

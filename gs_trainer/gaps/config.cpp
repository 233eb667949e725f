#include "gs_trainer/gaps/config.h"

#include <string>

#include <absl/strings/str_cat.h>
#include <nlohmann/json.hpp>
#include "common/json_fields.h"

namespace gaps {

// One list of fields for both directions, so JSON and struct cannot drift apart.
// clang-format off
#define GAPS_GAPS_CONFIG_FIELDS(X)                                                                        \
  X(warmup_iterations) X(phase_interval) X(pseudo_probability) X(n_active) X(tier_alpha_min)             \
  X(tier_alpha_max) X(alpha_step) X(max_extrap) X(interpolate_intrinsics) X(tier_upgrade_variance)       \
  X(tier_min_admitted) X(pose_rotation_weight) X(beta_start) X(beta_end) X(w_sparsity) X(w_entropy)      \
  X(w_novelty) X(novelty_gain) X(entropy_bins) X(gamma_hist) X(w_init) X(w_ref) X(init_coverage_weight)  \
  X(contrast_ref) X(coverage_alpha_threshold) X(ref_distance_scale) X(hist_variance_scale)               \
  X(diversity_radius) X(exploration_period) X(exploration_fraction) X(admit_min_alpha)                   \
  X(admit_max_residual) X(admit_min_structure) X(uncertainty_lambda) X(uncertainty_eps) X(extrap_kappa) X(pseudo_loss_weight)   \
  X(drop_max) X(drop_n_ref) X(strength_max) X(strength_min) X(cn_scale) X(cn_coverage)                   \
  X(ip_adapter_scale) X(lora_rank) X(lora_steps) X(inpaint_uncovered_fraction) X(inpaint_dilation) \
  X(inpaint_depth_threshold)
// clang-format on

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
  if (absl::Status s = validate_tiers(c); !s.ok()) return s;
  if (c.warmup_iterations < 0 || c.phase_interval <= 0) return invalid("bad schedule");
  if (c.pseudo_probability < 0 || c.pseudo_probability > 1) return invalid("pseudo_probability not in [0, 1]");
  if (c.n_active <= 0) return invalid("n_active must be positive");
  if (c.alpha_step <= 0) return invalid("alpha_step must be positive");
  if (c.entropy_bins < 2) return invalid("entropy_bins must be at least 2");
  if (c.beta_start < 0 || c.beta_end < 0) return invalid("beta must be non-negative");
  if (c.exploration_period <= 0) return invalid("exploration_period must be positive");
  if (c.exploration_fraction < 0 || c.exploration_fraction > 1) return invalid("exploration_fraction not in [0, 1]");
  if (c.drop_max < 0 || c.drop_max >= 1) return invalid("drop_max not in [0, 1)");  // 1/(1-r) compensation
  if (c.drop_n_ref <= 0 || c.cn_coverage <= 0 || c.contrast_ref <= 0 || c.ref_distance_scale <= 0 ||
      c.hist_variance_scale <= 0) {
    return invalid("scales must be positive");
  }
  const absl::Status inpaint = check_inpaint_settings(inpaint_settings(c));
  if (!inpaint.ok()) return invalid(std::string(inpaint.message()));
  for (const absl::Status& s :
       {check_scene_adaptation(scene_adaptation(c)), check_ip_adapter_scale(c.ip_adapter_scale)})
    if (!s.ok()) return invalid(std::string(s.message()));
  return absl::OkStatus();
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

void to_json(nlohmann::json& j, const GapsConfig& c) { GAPS_GAPS_CONFIG_FIELDS(GAPS_WRITE_FIELD) }

void from_json(const nlohmann::json& j, GapsConfig& c) {
  read_fields(j, "GAPS", [&](const std::string& key, const nlohmann::json& value) {
    GAPS_GAPS_CONFIG_FIELDS(GAPS_READ_FIELD)
    return false;
  });
  if (absl::Status s = validate_gaps_config(c); !s.ok()) {
    throw nlohmann::json::other_error::create(502, std::string(s.message()), &j);
  }
}

}  // namespace gaps

#include "gs_trainer/train_config.h"

#include <nlohmann/json.hpp>

namespace gaps {

// One list of fields for both directions, so JSON and struct cannot drift apart.
#define GAPS_TRAIN_CONFIG_FIELDS(X)                                                                        \
  X(iterations) X(seed) X(device) X(lambda_dssim) X(position_lr_init) X(position_lr_final)                 \
  X(feature_lr) X(opacity_lr) X(scaling_lr) X(rotation_lr) X(adam_eps)          \
  X(max_sh_degree) X(sh_increase_interval) X(densify_from_iter) X(densify_until_fraction)                  \
  X(densification_interval) X(opacity_reset_interval) X(densify_grad_threshold) X(absolute_gradient)      \
  X(percent_dense) X(min_opacity) X(max_screen_size) X(max_gaussians) X(gaussians_per_variation)        \
  X(prune_min_contribution) X(background)

void to_json(nlohmann::json& j, const TrainConfig& c) {
#define GAPS_TO_JSON(f) j[#f] = c.f;
  GAPS_TRAIN_CONFIG_FIELDS(GAPS_TO_JSON)
#undef GAPS_TO_JSON
}

void from_json(const nlohmann::json& j, TrainConfig& c) {
  for (auto it = j.begin(); it != j.end(); ++it) {
    bool known = false;
#define GAPS_FROM_JSON(f) \
  if (it.key() == #f) {   \
    it.value().get_to(c.f); \
    known = true;         \
  }
    GAPS_TRAIN_CONFIG_FIELDS(GAPS_FROM_JSON)
#undef GAPS_FROM_JSON
    if (!known) throw nlohmann::json::other_error::create(501, "unknown training option '" + it.key() + "'", &j);
  }
}

}  // namespace gaps

#include "gs_trainer/train/train_config.h"

#include <string>

#include <nlohmann/json.hpp>
#include "common/json_fields.h"

namespace gaps {

// One list of fields for both directions, so JSON and struct cannot drift apart.
// clang-format off
#define GAPS_TRAIN_CONFIG_FIELDS(X)                                                                        \
  X(iterations) X(seed) X(device) X(lambda_dssim) X(position_lr_init) X(position_lr_final)                 \
  X(feature_lr) X(opacity_lr) X(scaling_lr) X(rotation_lr) X(adam_eps)          \
  X(max_sh_degree) X(sh_increase_interval) X(densify_from_iter) X(densify_until_fraction)                  \
  X(densification_interval) X(opacity_reset_interval) X(densify_grad_threshold) X(absolute_gradient)      \
  X(percent_dense) X(min_opacity) X(max_screen_size) X(max_gaussians) X(gaussians_per_variation)        \
  X(prune_min_contribution) X(background)
// clang-format on

void to_json(nlohmann::json& j, const TrainConfig& c) { GAPS_TRAIN_CONFIG_FIELDS(GAPS_WRITE_FIELD) }

void from_json(const nlohmann::json& j, TrainConfig& c) {
  read_fields(j, "training", [&](const std::string& key, const nlohmann::json& value) {
    GAPS_TRAIN_CONFIG_FIELDS(GAPS_READ_FIELD)
    return false;
  });
}

}  // namespace gaps

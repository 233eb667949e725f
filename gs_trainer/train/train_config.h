#pragma once
// Every hyperparameter of a training run, with the defaults of the original 3DGS implementation where the
// paper follows it. Schedules given for 3DGS's 30k iterations are scaled to `iterations` where noted.
#include <cstdint>
#include <string>
#include <vector>

#include <absl/status/status.h>
#include <nlohmann/json_fwd.hpp>
#include "common/limits.h"
#include "common/option_table.h"

namespace gaps {

// clang-format off
// X(type, name, default, min, max, help): see common/option_table.h.
#define GAPS_TRAIN_CONFIG_OPTIONS(X)                                                                              \
  X(int, iterations, 10000, 1, 1e6, "total iterations T")                                                          \
  X(uint64_t, seed, 0, 0, 1.8446744073709552e19, "random seed of the run (initialisation, view order, dropout)")   \
  X(std::string, device, "cpu", 0, 0, "cpu, cuda or cuda:N")                                                       \
  /* Loss (paper eq. 3dgs_loss). */                                                                                \
  X(double, lambda_dssim, 0.2, 0, 1, "weight of D-SSIM in the photometric loss")                                   \
  /* Learning rates (3DGS). */                                                                                     \
  X(double, position_lr_init, 0.00016, 0, 1,                                                                       \
    "position learning rate at the start, times the cameras' extent; decays exponentially to the final rate")      \
  X(double, position_lr_final, 0.0000016, 0, 1, "position learning rate at the last iteration")                   \
  X(double, feature_lr, 0.0025, 0, 1, "SH DC learning rate; the higher-order coefficients use a twentieth")        \
  X(double, opacity_lr, 0.05, 0, 1, "opacity learning rate")                                                       \
  X(double, scaling_lr, 0.005, 0, 1, "scale learning rate")                                                        \
  X(double, rotation_lr, 0.001, 0, 1, "rotation learning rate")                                                    \
  X(double, adam_eps, 1e-15, 0, 1, "Adam's epsilon")                                                               \
  X(int, max_sh_degree, 3, 0, 3, "highest spherical-harmonics degree")                                             \
  X(int, sh_increase_interval, 1000, 1, 1e6, "the active SH degree rises by one every this many iterations")       \
  /* Adaptive density control (3DGS). */                                                                           \
  X(int, densify_from_iter, 500, 0, 1e6, "first iteration of densification")                                       \
  X(double, densify_until_fraction, 0.5, 0, 1,                                                                     \
    "densification stops at this fraction of the iterations (3DGS's 15k of 30k)")                                  \
  X(int, densification_interval, 100, 1, 1e6, "iterations between densification steps")                            \
  X(int, opacity_reset_interval, 0, 0, 1e6,                                                                        \
    "iterations between opacity resets while densifying; 0 = never (3DGS: 3000). Off by default: from 3 to 24 "    \
    "views every measured run ends 0.4-3.4 dB lower with the reset (docs/benchmarks.md, \"The opacity reset\")")   \
  X(double, densify_grad_threshold, 0.0002, 0, 1, "view-space gradient above which a Gaussian is densified")       \
  X(bool, absolute_gradient, false, 0, 0, "densify on the absolute-gradient criterion instead")                     \
  X(double, percent_dense, 0.01, 0, 1, "scale, relative to the scene extent, separating clone from split")         \
  X(double, min_opacity, 0.005, 0, 1, "Gaussians below this opacity are pruned")                                   \
  X(int, max_screen_size, 20, 0, 1e6, "prune screen-space radii above this after the first opacity reset")        \
  X(int64_t, max_gaussians, 0, 0, kMaxGaussians,                                                                   \
    "> 0: densification grows the model up to this many Gaussians, preferring the largest gradients; 0: the "      \
    "automatic budget (gaussians_per_variation) decides")                                                          \
  X(double, gaussians_per_variation, -1, -1, 1e6,                                                                  \
    "automatic Gaussian budget when max_gaussians is 0: this many per unit of the training views' total "          \
    "variation; 0 = unlimited growth as in 3DGS; < 0 (default) = 3.5, or 2 where --init auto reads the views at "  \
    "twice their size (forward-facing captures; gs_trainer/pipeline.h). 3.5 gives 31-46 % of 3DGS's model on "     \
    "fern and bonsai at equal or higher test PSNR (docs/benchmarks.md, \"A model no larger than the scene needs\")") \
  X(double, prune_min_contribution, 0.0, 0, 1e12,                                                                  \
    "at the end of densification, remove Gaussians whose blending weight summed over every pixel of every "        \
    "training view is below this many pixels; 0 = keep all")                                                       \
  X(double, background, 0.0, 0, 1, "background grey level composited behind the Gaussians (0 black, 1 white)")
// clang-format on

struct TrainConfig {
  GAPS_TRAIN_CONFIG_OPTIONS(GAPS_DECLARE_OPTION)

  int densify_until_iter() const { return static_cast<int>(densify_until_fraction * iterations); }
};

// Range checks from the option table, and a device name that parses.
absl::Status validate_train_config(const TrainConfig& c);
// Every option of TrainConfig, in table order.
std::vector<OptionInfo> train_config_options();

// from_json throws on unknown keys, wrong types and invalid values (validate_train_config).
void to_json(nlohmann::json& j, const TrainConfig& c);
void from_json(const nlohmann::json& j, TrainConfig& c);

}  // namespace gaps

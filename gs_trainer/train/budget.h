// The automatic Gaussian budget: how many Gaussians a scene needs, read off its training views.
//
// A Gaussian is needed where the image changes; flat regions are covered by a few large ones. The measure
// of change is the views' total variation (the sum over pixels of the grey-level gradient magnitude,
// intensities in [0, 1], central differences), so the budget is that sum times a density
// (TrainConfig::gaussians_per_variation; total_variation in eval/image_stats.h). Vanilla 3DGS grows about 7.5 to 11.5
// Gaussians per unit of it on fern and bonsai at -r 8 (docs/benchmarks.md, "A model no larger than the scene needs").
#pragma once

#include <cstdint>
#include <vector>

#include <ATen/core/Tensor.h>

namespace gaps {

struct TrainingView;

// The density a negative gaussians_per_variation (TrainConfig's default) stands for, where the pipeline does not
// choose another (with_auto_budget in gs_trainer/pipeline.h).
inline constexpr double kDefaultGaussiansPerVariation = 3.5;

// gaussians_per_variation × Σ_views total_variation, at least 1.
int64_t automatic_budget(const std::vector<TrainingView>& views, double gaussians_per_variation);

// The most Gaussians a run may grow to: max_gaussians when given (> 0), else the automatic budget (at
// kDefaultGaussiansPerVariation when gaussians_per_variation < 0), or 0 (no limit) when gaussians_per_variation is 0.
int64_t gaussian_budget(int64_t max_gaussians, double gaussians_per_variation, const std::vector<TrainingView>& views);

}  // namespace gaps

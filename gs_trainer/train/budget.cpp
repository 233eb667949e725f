#include "gs_trainer/train/budget.h"

#include <algorithm>
#include <cmath>

#include <ATen/ATen.h>
#include "gs_trainer/eval/image_stats.h"
#include "gs_trainer/train/trainer.h"

namespace gaps {

int64_t automatic_budget(const std::vector<TrainingView>& views, double gaussians_per_variation) {
  TORCH_CHECK(gaussians_per_variation > 0, "the automatic budget needs gaussians_per_variation > 0, got ",
              gaussians_per_variation);
  double variation = 0.0;
  for (const auto& v : views) variation += total_variation(v.image);
  return std::max<int64_t>(1, std::llround(gaussians_per_variation * variation));
}

int64_t gaussian_budget(int64_t max_gaussians, double gaussians_per_variation, const std::vector<TrainingView>& views) {
  if (max_gaussians > 0 || gaussians_per_variation == 0) return std::max<int64_t>(max_gaussians, 0);  // a count wins
  return automatic_budget(views, gaussians_per_variation < 0 ? kDefaultGaussiansPerVariation : gaussians_per_variation);
}

}  // namespace gaps

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

}  // namespace gaps

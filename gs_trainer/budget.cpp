#include "gs_trainer/budget.h"

#include <algorithm>
#include <cmath>

#include <ATen/ATen.h>
#include "gs_trainer/gaps_scores.h"
#include "gs_trainer/trainer.h"

namespace gaps {

double total_variation(const at::Tensor& image) {
  const at::Tensor grey = greyscale(image).to(at::kDouble);
  const int64_t h = grey.size(0), w = grey.size(1);
  at::Tensor gx = at::zeros_like(grey), gy = at::zeros_like(grey);
  if (w > 2) gx.narrow(1, 1, w - 2).copy_((grey.narrow(1, 2, w - 2) - grey.narrow(1, 0, w - 2)) * 0.5);
  if (h > 2) gy.narrow(0, 1, h - 2).copy_((grey.narrow(0, 2, h - 2) - grey.narrow(0, 0, h - 2)) * 0.5);
  return at::sqrt(gx.square() + gy.square()).sum().item<double>();
}

int64_t automatic_budget(const std::vector<TrainingView>& views, double gaussians_per_variation) {
  TORCH_CHECK(gaussians_per_variation > 0, "the automatic budget needs gaussians_per_variation > 0, got ",
              gaussians_per_variation);
  double variation = 0.0;
  for (const auto& v : views) variation += total_variation(v.image);
  return std::max<int64_t>(1, std::llround(gaussians_per_variation * variation));
}

}  // namespace gaps

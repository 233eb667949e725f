#pragma once
// A small model for the optimiser and density-control tests (trainer_test.cpp and gpu/).
#include <cmath>

#include <ATen/ATen.h>
#include "gs_trainer/model/gaussians.h"

namespace gaps::test {

// n small round unrotated Gaussians with means 0.1 apart, opacity logits and SH coefficients zero, SH degree 1.
inline GaussianModel tiny_model(int n) {
  GaussianModel m;
  m.max_sh_degree = 1;
  m.means = at::arange(3 * n, at::kFloat).view({n, 3}) * 0.1;
  m.log_scales = at::full({n, 3}, std::log(0.01f));
  m.quats = at::zeros({n, 4});
  m.quats.select(1, 0).fill_(1.0);
  m.opacity_logits = at::zeros({n});
  m.sh_dc = at::zeros({n, 1, 3});
  m.sh_rest = at::zeros({n, 3, 3});
  return m;
}

}  // namespace gaps::test

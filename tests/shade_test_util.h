#pragma once
// Inputs of shade_gaussians, shared by its CPU tests (shade_test.cpp) and its CUDA test (gpu/).
#include <array>
#include <cstdint>

#include <ATen/ATen.h>

namespace gaps::test {

struct ShadeInputs {
  at::Tensor means, dc, rest;
  std::array<double, 3> centre{0.3, -0.2, -1.5};
};

// Colours straddle 0 so the clamp is exercised; one Gaussian sits almost on the centre.
inline ShadeInputs random_shade_inputs(int64_t n, at::ScalarType dtype, uint64_t seed) {
  at::manual_seed(seed);
  const auto o = at::TensorOptions().dtype(dtype);
  ShadeInputs in;
  in.means = at::randn({n, 3}, o) * 2.0;
  in.means[0] = at::tensor({0.3 + 1e-3, -0.2, -1.5}, o);
  in.dc = at::randn({n, 1, 3}, o) * 1.5;
  in.rest = at::randn({n, 15, 3}, o) * 0.4;
  return in;
}

}  // namespace gaps::test

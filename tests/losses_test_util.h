#pragma once
// Images for the loss tests (losses_test.cpp and gpu/).
#include <cstdint>

#include <ATen/ATen.h>

namespace gaps::test {

// H x W x 3 in double, uniform in [lo, hi), the same for the same seed.
inline at::Tensor random_image(int64_t h, int64_t w, uint64_t seed, double lo = 0.0, double hi = 1.0) {
  at::Generator gen = at::make_generator<at::CPUGeneratorImpl>(seed);
  return at::rand({h, w, 3}, gen, at::TensorOptions().dtype(at::kDouble)) * (hi - lo) + lo;
}

}  // namespace gaps::test

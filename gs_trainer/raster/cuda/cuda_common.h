#pragma once
// Checks and launch arithmetic shared by the element-wise kernels of this folder.
#include <cstdint>

#include <ATen/core/Tensor.h>
#include <c10/util/Exception.h>

namespace gaps::backend {

// The kernels compute in float32; double precision (gradient checks) is the CPU backend's job.
inline void check_cuda_float(const char* name, const at::Tensor& t) {
  TORCH_CHECK(t.is_cuda(), name, " must be a CUDA tensor");
  TORCH_CHECK(t.scalar_type() == at::kFloat, "the CUDA kernels compute in float32 only; ", name, " is ",
              t.scalar_type(), " (use the CPU backend for double precision)");
}

constexpr int kElementwiseThreads = 256;

inline unsigned int blocks_for(int64_t n, int threads = kElementwiseThreads) {
  return static_cast<unsigned int>((n + threads - 1) / threads);
}

}  // namespace gaps::backend

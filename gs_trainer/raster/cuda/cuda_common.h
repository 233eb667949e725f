#pragma once
// Checks, launch arithmetic and template dispatch shared by the kernels of this folder.
#include <cstdint>
#include <initializer_list>
#include <type_traits>

#include <ATen/core/Tensor.h>
#include <c10/util/Exception.h>

namespace gaps::backend {

// The kernels compute in float32; double precision (gradient checks) is the CPU backend's job.
inline void check_cuda_float(const char* name, const at::Tensor& t) {
  TORCH_CHECK(t.is_cuda(), name, " must be a CUDA tensor");
  TORCH_CHECK(t.scalar_type() == at::kFloat, "the CUDA kernels compute in float32 only; ", name, " is ",
              t.scalar_type(), " (use the CPU backend for double precision)");
}

// The compositing passes' inputs: float32 CUDA tensors, or an error that says what to use instead.
inline void check_raster_inputs(std::initializer_list<const at::Tensor*> tensors) {
  for (const at::Tensor* t : tensors)
    TORCH_CHECK(t->is_cuda() && t->scalar_type() == at::kFloat, "the CUDA rasterizer computes in float32 only, got a ",
                t->scalar_type(), " tensor on ", t->device(), " (use the CPU backend for double precision)");
}

constexpr int kElementwiseThreads = 256;

inline unsigned int blocks_for(int64_t n, int threads = kElementwiseThreads) {
  return static_cast<unsigned int>((n + threads - 1) / threads);
}

// The compositing kernels keep a pixel's feature channels in registers, so they are compiled for a channel
// capacity: 4 covers colour + depth (what render() composites); 16 is the general case. Calls
// f(std::integral_constant<int, capacity>) for the smallest capacity that holds `channels`.
template <typename F>
void dispatch_channels(int channels, F&& f) {
  TORCH_CHECK(channels >= 1 && channels <= 16, "the CUDA rasterizer composites 1 to 16 feature channels, got ",
              channels);
  if (channels <= 4)
    f(std::integral_constant<int, 4>{});
  else
    f(std::integral_constant<int, 16>{});
}

}  // namespace gaps::backend

#pragma once
// Checks, launch arithmetic, template dispatch and the compositing passes' common inputs, shared by the kernels
// of this folder.
#include <cstdint>
#include <initializer_list>
#include <type_traits>

#include <ATen/core/Tensor.h>
#include <c10/util/Exception.h>

#include "gs_trainer/raster/raster_math.h"

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

// The most views one launch of the stacked-view kernels (projection, shading) carries parameters for, by value.
constexpr int kMaxViews = 32;

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

// What both compositing passes read: the image and its tile grid, the tiles' Gaussian lists and the splats.
struct CompositeInputs {
  int width, height, tiles_x, channels;
  const int32_t* __restrict__ ranges;
  const int32_t* __restrict__ ids;
  const float* __restrict__ means2d;
  const float* __restrict__ conics;
  const float* __restrict__ opacities;
  const float* __restrict__ features;
};

// Pointers into contiguous float32 (int32: ranges, ids) CUDA tensors, which must outlive the launch.
inline CompositeInputs composite_inputs(int width, int height, int tiles_x, const at::Tensor& ranges,
                                        const at::Tensor& ids, const at::Tensor& means2d, const at::Tensor& conics,
                                        const at::Tensor& opacities, const at::Tensor& features) {
  return {width,
          height,
          tiles_x,
          static_cast<int>(features.size(1)),
          ranges.data_ptr<int32_t>(),
          ids.data_ptr<int32_t>(),
          means2d.data_ptr<float>(),
          conics.data_ptr<float>(),
          opacities.data_ptr<float>(),
          features.data_ptr<float>()};
}

// One Gaussian of a compositing batch as the kernels stage it in shared memory: two 16-byte loads per (pixel,
// Gaussian) pair instead of five, and the exponent below which the pair is skipped without an exp
// (raster::certain_skip_power).
struct StagedSplat {
  float4 mean_conic_ab;    // mean.x, mean.y, conic.a, conic.b
  float4 conic_c_opacity;  // conic.c, opacity, skip power, unused
};

#if defined(__CUDACC__)
__device__ __forceinline__ StagedSplat stage_splat(const CompositeInputs& a, int g) {
  const float opacity = a.opacities[g];
  return {make_float4(a.means2d[2 * g], a.means2d[2 * g + 1], a.conics[3 * g], a.conics[3 * g + 1]),
          make_float4(a.conics[3 * g + 2], opacity, raster::certain_skip_power(opacity), 0.f)};
}

// The exponent of the staged Gaussian at pixel centre (cx, cy), and the offsets (as raster::gaussian_power).
__device__ __forceinline__ float staged_power(const StagedSplat& s, float cx, float cy, float& dx, float& dy) {
  return raster::gaussian_power<float>({s.mean_conic_ab.x, s.mean_conic_ab.y},
                                       {s.mean_conic_ab.z, s.mean_conic_ab.w, s.conic_c_opacity.x}, cx, cy, dx, dy);
}
#endif

}  // namespace gaps::backend

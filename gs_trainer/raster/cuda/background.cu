// The background compositing on the GPU: one thread per pixel each way, where the ATen operations were five
// launches forward and six backward (with their autograd bookkeeping) in every training step.
#include <ATen/core/Tensor.h>
#include <ATen/cuda/CUDAContext.h>
#include <ATen/ops/empty.h>
#include <c10/cuda/CUDAGuard.h>

#include "gs_trainer/raster/cuda/cuda_common.h"
#include "gs_trainer/raster/rasterize_backend.h"

namespace gaps::backend {
namespace {

__global__ void over_background_forward_kernel(int64_t pixels, int channels, const float* __restrict__ features,
                                               const float* __restrict__ alpha, const float* __restrict__ background,
                                               float* __restrict__ rgb) {
  const int64_t p = static_cast<int64_t>(blockIdx.x) * blockDim.x + threadIdx.x;
  if (p >= pixels) return;
  const float behind = 1 - alpha[p];
  for (int c = 0; c < 3; ++c) rgb[3 * p + c] = features[p * channels + c] + behind * background[c];
}

__global__ void over_background_backward_kernel(int64_t pixels, int channels, const float* __restrict__ g_rgb,
                                                const float* __restrict__ background, float* __restrict__ g_features,
                                                float* __restrict__ g_alpha) {
  const int64_t p = static_cast<int64_t>(blockIdx.x) * blockDim.x + threadIdx.x;
  if (p >= pixels) return;
  float g_behind = 0.f;
  for (int c = 0; c < 3; ++c) {
    const float g = g_rgb[3 * p + c];
    g_features[p * channels + c] = g;
    g_behind += g * background[c];
  }
  for (int c = 3; c < channels; ++c) g_features[p * channels + c] = 0.f;
  g_alpha[p] = -g_behind;
}

void check_background(const at::Tensor& background) {
  check_cuda_float("background", background);
  TORCH_CHECK(background.numel() == 3, "the background must be 3 values, got ", background.sizes());
}

}  // namespace

at::Tensor over_background_forward_cuda(const at::Tensor& features_in, const at::Tensor& alpha_in,
                                        const at::Tensor& background_in) {
  check_raster_inputs({&features_in, &alpha_in});
  check_background(background_in);
  TORCH_CHECK(features_in.dim() == 3 && features_in.size(2) >= 3 && alpha_in.dim() == 2 &&
                  alpha_in.size(0) == features_in.size(0) && alpha_in.size(1) == features_in.size(1),
              "over_background: features H x W x C (C >= 3) and alpha H x W expected, got ", features_in.sizes(),
              " and ", alpha_in.sizes());
  const c10::cuda::CUDAGuard guard(features_in.device());
  const auto features = features_in.contiguous(), alpha = alpha_in.contiguous();
  const auto background = background_in.contiguous();
  const int64_t pixels = alpha.numel();
  at::Tensor rgb = at::empty({features.size(0), features.size(1), 3}, features.options());
  if (pixels == 0) return rgb;
  over_background_forward_kernel<<<blocks_for(pixels), kElementwiseThreads, 0, at::cuda::getCurrentCUDAStream()>>>(
      pixels, static_cast<int>(features.size(2)), features.data_ptr<float>(), alpha.data_ptr<float>(),
      background.data_ptr<float>(), rgb.data_ptr<float>());
  C10_CUDA_KERNEL_LAUNCH_CHECK();
  return rgb;
}

BackgroundGrads over_background_backward_cuda(const at::Tensor& g_rgb_in, const at::Tensor& background_in,
                                              int64_t channels) {
  check_raster_inputs({&g_rgb_in});
  check_background(background_in);
  TORCH_CHECK(g_rgb_in.dim() == 3 && g_rgb_in.size(2) == 3 && channels >= 3,
              "over_background: an H x W x 3 gradient of at least 3 channels expected, got ", g_rgb_in.sizes());
  const c10::cuda::CUDAGuard guard(g_rgb_in.device());
  const auto g_rgb = g_rgb_in.contiguous(), background = background_in.contiguous();
  const int64_t h = g_rgb.size(0), w = g_rgb.size(1), pixels = h * w;
  BackgroundGrads g{at::empty({h, w, channels}, g_rgb.options()), at::empty({h, w}, g_rgb.options())};
  if (pixels == 0) return g;
  over_background_backward_kernel<<<blocks_for(pixels), kElementwiseThreads, 0, at::cuda::getCurrentCUDAStream()>>>(
      pixels, static_cast<int>(channels), g_rgb.data_ptr<float>(), background.data_ptr<float>(),
      g.features.data_ptr<float>(), g.alpha.data_ptr<float>());
  C10_CUDA_KERNEL_LAUNCH_CHECK();
  return g;
}

}  // namespace gaps::backend

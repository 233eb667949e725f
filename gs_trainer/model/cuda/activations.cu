// The model's activations on the GPU: one thread per Gaussian each way.
#include <ATen/core/Tensor.h>
#include <ATen/cuda/CUDAContext.h>
#include <ATen/ops/empty_like.h>
#include <c10/cuda/CUDAGuard.h>

#include "gs_trainer/model/cuda/activations_cuda.h"
#include "gs_trainer/raster/cuda/cuda_common.h"

namespace gaps::backend {
namespace {

__global__ void activations_forward_kernel(int64_t n, const float* __restrict__ log_scales,
                                           const float* __restrict__ logits, const float* __restrict__ opacity_scale,
                                           float* __restrict__ scales, float* __restrict__ sigmoid,
                                           float* __restrict__ opacities) {
  const int64_t i = static_cast<int64_t>(blockIdx.x) * blockDim.x + threadIdx.x;
  if (i >= n) return;
  for (int k = 0; k < 3; ++k) scales[3 * i + k] = expf(log_scales[3 * i + k]);
  const float s = 1.f / (1.f + expf(-logits[i]));
  sigmoid[i] = s;
  if (opacity_scale != nullptr) opacities[i] = s * opacity_scale[i];
}

__global__ void activations_backward_kernel(int64_t n, const float* __restrict__ g_scales,
                                            const float* __restrict__ g_opacities, const float* __restrict__ scales,
                                            const float* __restrict__ sigmoid, const float* __restrict__ opacity_scale,
                                            float* __restrict__ g_log_scales, float* __restrict__ g_logits) {
  const int64_t i = static_cast<int64_t>(blockIdx.x) * blockDim.x + threadIdx.x;
  if (i >= n) return;
  if (g_scales != nullptr)
    for (int k = 0; k < 3; ++k) g_log_scales[3 * i + k] = g_scales[3 * i + k] * scales[3 * i + k];
  if (g_opacities != nullptr) {
    const float g = opacity_scale != nullptr ? g_opacities[i] * opacity_scale[i] : g_opacities[i];
    const float s = sigmoid[i];
    g_logits[i] = g * (1.f - s) * s;
  }
}

// A defined float32 tensor of `numel` values on `device`, made contiguous; nullptr (and `holder` left undefined)
// for an undefined one.
const float* optional_input(const char* name, const at::Tensor& t, int64_t numel, const c10::Device& device,
                            at::Tensor& holder) {
  if (!t.defined()) return nullptr;
  check_cuda_float(name, t);
  TORCH_CHECK(t.device() == device && t.numel() == numel, name, ": ", numel, " values on ", device, " expected, got ",
              t.sizes(), " on ", t.device());
  holder = t.contiguous();
  return holder.data_ptr<float>();
}

}  // namespace

Activations activations_forward_cuda(const at::Tensor& log_scales_in, const at::Tensor& logits_in,
                                     const at::Tensor& opacity_scale_in) {
  check_cuda_float("log_scales", log_scales_in);
  TORCH_CHECK(logits_in.defined(), "activations: the opacity logits are undefined");
  const int64_t n = logits_in.numel();
  TORCH_CHECK(log_scales_in.dim() == 2 && log_scales_in.size(0) == n && log_scales_in.size(1) == 3,
              "activations: log_scales N x 3 and N logits expected, got ", log_scales_in.sizes(), " and ",
              logits_in.sizes());
  const c10::cuda::CUDAGuard guard(log_scales_in.device());
  at::Tensor logits, scale;
  const float* logits_ptr = optional_input("logits", logits_in, n, log_scales_in.device(), logits);
  const float* scale_ptr = optional_input("opacity_scale", opacity_scale_in, n, log_scales_in.device(), scale);
  const auto log_scales = log_scales_in.contiguous();
  Activations out;
  out.scales = at::empty_like(log_scales);
  out.sigmoid = at::empty_like(logits);
  out.opacities = scale_ptr != nullptr ? at::empty_like(logits) : out.sigmoid;
  if (n == 0) return out;
  activations_forward_kernel<<<blocks_for(n), kElementwiseThreads, 0, at::cuda::getCurrentCUDAStream()>>>(
      n, log_scales.data_ptr<float>(), logits_ptr, scale_ptr, out.scales.data_ptr<float>(),
      out.sigmoid.data_ptr<float>(), out.opacities.data_ptr<float>());
  C10_CUDA_KERNEL_LAUNCH_CHECK();
  return out;
}

ActivationGrads activations_backward_cuda(const at::Tensor& g_scales_in, const at::Tensor& g_opacities_in,
                                          const at::Tensor& scales_in, const at::Tensor& sigmoid_in,
                                          const at::Tensor& opacity_scale_in) {
  check_cuda_float("scales", scales_in);
  const int64_t n = sigmoid_in.numel();
  const c10::Device device = scales_in.device();
  const c10::cuda::CUDAGuard guard(device);
  at::Tensor g_scales, g_opacities, scales, sigmoid, scale;
  const float* g_scales_ptr = optional_input("dL/dscales", g_scales_in, 3 * n, device, g_scales);
  const float* g_opacities_ptr = optional_input("dL/dopacities", g_opacities_in, n, device, g_opacities);
  const float* scales_ptr = optional_input("scales", scales_in, 3 * n, device, scales);
  const float* sigmoid_ptr = optional_input("sigmoid", sigmoid_in, n, device, sigmoid);
  const float* scale_ptr = optional_input("opacity_scale", opacity_scale_in, n, device, scale);
  ActivationGrads g;
  if (g_scales_ptr != nullptr) g.log_scales = at::empty_like(scales);
  if (g_opacities_ptr != nullptr) g.logits = at::empty_like(sigmoid);
  if (n == 0 || (g_scales_ptr == nullptr && g_opacities_ptr == nullptr)) return g;
  activations_backward_kernel<<<blocks_for(n), kElementwiseThreads, 0, at::cuda::getCurrentCUDAStream()>>>(
      n, g_scales_ptr, g_opacities_ptr, scales_ptr, sigmoid_ptr, scale_ptr,
      g_scales_ptr != nullptr ? g.log_scales.data_ptr<float>() : nullptr,
      g_opacities_ptr != nullptr ? g.logits.data_ptr<float>() : nullptr);
  C10_CUDA_KERNEL_LAUNCH_CHECK();
  return g;
}

}  // namespace gaps::backend

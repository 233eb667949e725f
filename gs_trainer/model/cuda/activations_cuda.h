#pragma once
// The model's activations on the GPU, for render.cpp to pick for CUDA float32 models: scales = exp(log_scales),
// opacities = sigmoid(logits) [* opacity_scale], and their backward, one kernel each way (the ATen operations were
// two or three launches each way in every training step). Only builds with CUDA kernels (GAPS_CUDA_KERNELS)
// define them.
#include <ATen/Tensor.h>

namespace gaps::backend {

struct Activations {
  at::Tensor scales;     // N x 3
  at::Tensor sigmoid;    // N, sigmoid(logits)
  at::Tensor opacities;  // N, sigmoid * opacity_scale, or `sigmoid` itself without a scale
};
// log_scales N x 3, logits N, opacity_scale N or undefined (1).
Activations activations_forward_cuda(const at::Tensor& log_scales, const at::Tensor& logits,
                                     const at::Tensor& opacity_scale);

struct ActivationGrads {
  at::Tensor log_scales, logits;  // undefined where the matching output gradient is
};
// g_log_scales = g_scales * scales; g_logits = (g_opacities [* opacity_scale]) * sigmoid * (1 - sigmoid), the
// formulas of autograd's ExpBackward, MulBackward and sigmoid_backward.
ActivationGrads activations_backward_cuda(const at::Tensor& g_scales, const at::Tensor& g_opacities,
                                          const at::Tensor& scales, const at::Tensor& sigmoid,
                                          const at::Tensor& opacity_scale);

}  // namespace gaps::backend

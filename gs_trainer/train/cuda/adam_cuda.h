#pragma once
// One fused Adam update per parameter tensor on the GPU, for adam.cpp to pick for CUDA tensors. Only builds
// with CUDA kernels (GAPS_CUDA_KERNELS) define it.
#include <ATen/Tensor.h>

namespace gaps::backend {

struct AdamStep {
  double lr, beta1, beta2, eps;
  double bias_correction1, bias_correction2;  // 1 - beta^t
};

// In place: exp_avg, exp_avg_sq and param, exactly the update of GaussianAdam::step on the CPU.
void adam_update_cuda(at::Tensor& param, const at::Tensor& grad, at::Tensor& exp_avg, at::Tensor& exp_avg_sq,
                      const AdamStep& step);

}  // namespace gaps::backend

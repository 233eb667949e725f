#pragma once
// The fused Adam update on the GPU, for adam.cpp to pick for CUDA tensors: every parameter tensor of a step in one
// launch. Only builds with CUDA kernels (GAPS_CUDA_KERNELS) define it.
#include <vector>

#include <ATen/Tensor.h>

namespace gaps::backend {

struct AdamStep {
  double lr, beta1, beta2, eps;
  double bias_correction1, bias_correction2;  // 1 - beta^t
};

// One parameter tensor's update: its values, gradient and moments (float32, contiguous, one CUDA device, equal
// sizes) and its step's constants.
struct AdamTensors {
  at::Tensor param, grad, exp_avg, exp_avg_sq;
  AdamStep step;
};

// In place: exp_avg, exp_avg_sq and param of every entry, each exactly the update of GaussianAdam::step on the
// CPU; one kernel launch for up to eight tensors (a model's six in one).
void adam_update_cuda(std::vector<AdamTensors>& updates);

}  // namespace gaps::backend

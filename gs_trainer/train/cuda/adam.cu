// Adam on the GPU: the element-wise update of every parameter tensor of a step in one kernel launch (a flat
// index over the tensors one after another), instead of six ATen launches per tensor or one launch per tensor.
// The launches, not the arithmetic, were the cost: 3DGS trains six small tensors every iteration.
#include <cmath>

#include <ATen/core/Tensor.h>
#include <ATen/cuda/CUDAContext.h>
#include <c10/cuda/CUDAGuard.h>

#include "gs_trainer/raster/cuda/cuda_common.h"
#include "gs_trainer/train/cuda/adam_cuda.h"

namespace gaps::backend {
namespace {

constexpr int kMaxTensors = 8;

struct AdamConstants {
  float beta1, one_minus_beta1, beta2, one_minus_beta2, eps, inv_sqrt_bc2, step_size;
};

struct AdamBatch {
  int count;
  int64_t end[kMaxTensors];  // tensor t covers the flat indices [end[t - 1], end[t])
  AdamConstants k[kMaxTensors];
  float* param[kMaxTensors];
  const float* grad[kMaxTensors];
  float* exp_avg[kMaxTensors];
  float* exp_avg_sq[kMaxTensors];
};

__global__ void adam_kernel(const AdamBatch b) {
  const int64_t flat = static_cast<int64_t>(blockIdx.x) * blockDim.x + threadIdx.x;
  int t = 0;
  while (t < b.count && flat >= b.end[t]) ++t;
  if (t == b.count) return;
  const int64_t i = flat - (t == 0 ? 0 : b.end[t - 1]);
  const AdamConstants& k = b.k[t];
  const float g = b.grad[t][i];
  const float m = b.exp_avg[t][i] * k.beta1 + g * k.one_minus_beta1;
  const float v = b.exp_avg_sq[t][i] * k.beta2 + g * g * k.one_minus_beta2;
  b.exp_avg[t][i] = m;
  b.exp_avg_sq[t][i] = v;
  b.param[t][i] -= k.step_size * m / (sqrtf(v) * k.inv_sqrt_bc2 + k.eps);
}

AdamConstants constants_of(const AdamStep& s) {
  return {float(s.beta1),
          float(1 - s.beta1),
          float(s.beta2),
          float(1 - s.beta2),
          float(s.eps),
          float(1 / std::sqrt(s.bias_correction2)),
          float(s.lr / s.bias_correction1)};
}

void check_update(const AdamTensors& u, const c10::Device& device) {
  for (const at::Tensor* t : {&u.param, &u.grad, &u.exp_avg, &u.exp_avg_sq}) {
    check_cuda_float("Adam tensor", *t);
    TORCH_CHECK(t->device() == device, "the fused Adam update needs all tensors on one device, got ", t->device(),
                " and ", device);
    TORCH_CHECK(t->is_contiguous(), "the fused Adam update needs contiguous tensors");
    TORCH_CHECK(t->numel() == u.param.numel(), "Adam state and gradient must match the parameter's size");
  }
}

void launch(const AdamBatch& b) {
  const int64_t n = b.count == 0 ? 0 : b.end[b.count - 1];
  if (n == 0) return;
  adam_kernel<<<blocks_for(n), kElementwiseThreads, 0, at::cuda::getCurrentCUDAStream()>>>(b);
  C10_CUDA_KERNEL_LAUNCH_CHECK();
}

}  // namespace

void adam_update_cuda(std::vector<AdamTensors>& updates) {
  if (updates.empty()) return;
  const c10::Device device = updates.front().param.device();
  const c10::cuda::CUDAGuard guard(device);
  AdamBatch batch{};
  int64_t total = 0;
  for (AdamTensors& u : updates) {
    check_update(u, device);
    if (batch.count == kMaxTensors) {
      launch(batch);
      batch = AdamBatch{};
      total = 0;
    }
    const int t = batch.count++;
    total += u.param.numel();
    batch.end[t] = total;
    batch.k[t] = constants_of(u.step);
    batch.param[t] = u.param.data_ptr<float>();
    batch.grad[t] = u.grad.data_ptr<float>();
    batch.exp_avg[t] = u.exp_avg.data_ptr<float>();
    batch.exp_avg_sq[t] = u.exp_avg_sq.data_ptr<float>();
  }
  launch(batch);
}

}  // namespace gaps::backend

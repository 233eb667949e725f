// Adam on the GPU: one element-wise kernel per parameter tensor instead of the six ATen launches of the
// same update (3DGS trains six tensors, so ~36 launches per iteration become 6).
#include <cmath>

#include <ATen/core/Tensor.h>
#include <ATen/cuda/CUDAContext.h>
#include <c10/cuda/CUDAGuard.h>

#include "gs_trainer/raster/cuda/cuda_common.h"
#include "gs_trainer/train/cuda/adam_cuda.h"

namespace gaps::backend {
namespace {

struct AdamConstants {
  float beta1, one_minus_beta1, beta2, one_minus_beta2, eps, inv_sqrt_bc2, step_size;
};

__global__ void adam_kernel(int64_t n, AdamConstants k, float* __restrict__ param, const float* __restrict__ grad,
                            float* __restrict__ exp_avg, float* __restrict__ exp_avg_sq) {
  const int64_t i = static_cast<int64_t>(blockIdx.x) * blockDim.x + threadIdx.x;
  if (i >= n) return;
  const float g = grad[i];
  const float m = exp_avg[i] * k.beta1 + g * k.one_minus_beta1;
  const float v = exp_avg_sq[i] * k.beta2 + g * g * k.one_minus_beta2;
  exp_avg[i] = m;
  exp_avg_sq[i] = v;
  param[i] -= k.step_size * m / (sqrtf(v) * k.inv_sqrt_bc2 + k.eps);
}

}  // namespace

void adam_update_cuda(at::Tensor& param, const at::Tensor& grad, at::Tensor& exp_avg, at::Tensor& exp_avg_sq,
                      const AdamStep& step) {
  check_cuda_float("parameter", param);
  check_cuda_float("gradient", grad);
  TORCH_CHECK(param.is_contiguous() && grad.is_contiguous() && exp_avg.is_contiguous() && exp_avg_sq.is_contiguous(),
              "the fused Adam update needs contiguous tensors");
  TORCH_CHECK(grad.numel() == param.numel() && exp_avg.numel() == param.numel() && exp_avg_sq.numel() == param.numel(),
              "Adam state and gradient must match the parameter's size");
  const int64_t n = param.numel();
  if (n == 0) return;
  const c10::cuda::CUDAGuard guard(param.device());
  const AdamConstants k{float(step.beta1),
                        float(1 - step.beta1),
                        float(step.beta2),
                        float(1 - step.beta2),
                        float(step.eps),
                        float(1 / std::sqrt(step.bias_correction2)),
                        float(step.lr / step.bias_correction1)};
  adam_kernel<<<blocks_for(n), kElementwiseThreads, 0, at::cuda::getCurrentCUDAStream()>>>(
      n, k, param.data_ptr<float>(), grad.data_ptr<float>(), exp_avg.data_ptr<float>(), exp_avg_sq.data_ptr<float>());
  C10_CUDA_KERNEL_LAUNCH_CHECK();
}

}  // namespace gaps::backend

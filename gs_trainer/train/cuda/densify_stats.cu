// Densification's per-step statistics on the GPU: one thread per Gaussian.
#include <ATen/core/Tensor.h>
#include <ATen/cuda/CUDAContext.h>
#include <c10/cuda/CUDAGuard.h>

#include "gs_trainer/raster/cuda/cuda_common.h"
#include "gs_trainer/train/cuda/densify_stats_cuda.h"

namespace gaps::backend {
namespace {

__global__ void accumulate_kernel(int64_t n, const float* __restrict__ grad, const int32_t* __restrict__ radii,
                                  float half_width, float half_height, float* __restrict__ grad_accum,
                                  float* __restrict__ denom, int32_t* __restrict__ max_radii) {
  const int64_t i = static_cast<int64_t>(blockIdx.x) * blockDim.x + threadIdx.x;
  if (i >= n) return;
  const int32_t r = radii[i];
  if (r <= 0) return;
  grad_accum[i] += hypotf(grad[2 * i] * half_width, grad[2 * i + 1] * half_height);
  denom[i] += 1.f;
  if (r > max_radii[i]) max_radii[i] = r;
}

}  // namespace

void accumulate_view_gradients_cuda(const at::Tensor& grad_in, const at::Tensor& radii_in, int width, int height,
                                    at::Tensor& grad_accum, at::Tensor& denom, at::Tensor& max_radii) {
  check_cuda_float("the 2D-mean gradient", grad_in);
  check_cuda_float("the gradient sums", grad_accum);
  check_cuda_float("the visibility counts", denom);
  const int64_t n = radii_in.numel();
  TORCH_CHECK(radii_in.is_cuda() && radii_in.scalar_type() == at::kInt && max_radii.is_cuda() &&
                  max_radii.scalar_type() == at::kInt,
              "accumulate_view_gradients_cuda: radii and max_radii must be int32 CUDA tensors");
  TORCH_CHECK(grad_in.dim() == 2 && grad_in.size(0) == n && grad_in.size(1) == 2 && grad_accum.numel() == n &&
                  denom.numel() == n && max_radii.numel() == n,
              "accumulate_view_gradients_cuda: N x 2 gradients and N-value statistics expected, got ", grad_in.sizes(),
              " for ", n, " radii");
  TORCH_CHECK(grad_accum.is_contiguous() && denom.is_contiguous() && max_radii.is_contiguous(),
              "accumulate_view_gradients_cuda: the statistics must be contiguous");
  if (n == 0) return;
  const c10::cuda::CUDAGuard guard(grad_in.device());
  const auto grad = grad_in.contiguous(), radii = radii_in.contiguous();
  accumulate_kernel<<<blocks_for(n), kElementwiseThreads, 0, at::cuda::getCurrentCUDAStream()>>>(
      n, grad.data_ptr<float>(), radii.data_ptr<int32_t>(), 0.5f * static_cast<float>(width),
      0.5f * static_cast<float>(height), grad_accum.data_ptr<float>(), denom.data_ptr<float>(),
      max_radii.data_ptr<int32_t>());
  C10_CUDA_KERNEL_LAUNCH_CHECK();
}

}  // namespace gaps::backend

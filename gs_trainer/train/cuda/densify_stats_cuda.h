#pragma once
// Densification's per-step statistics on the GPU, for densify.cpp to pick for CUDA tensors. Only builds with CUDA
// kernels (GAPS_CUDA_KERNELS) define it.
#include <ATen/Tensor.h>

namespace gaps::backend {

// For every Gaussian i with radii[i] > 0: grad_accum[i] += hypot(grad[i][0] * width / 2, grad[i][1] * height / 2),
// denom[i] += 1, max_radii[i] = max(max_radii[i], radii[i]); in place, one kernel (DensityControl::accumulate's ATen
// operations were eight launches every step until densification ends). grad N x 2 and the sums N float32, radii
// and max_radii N int32, all on one CUDA device.
void accumulate_view_gradients_cuda(const at::Tensor& grad, const at::Tensor& radii, int width, int height,
                                    at::Tensor& grad_accum, at::Tensor& denom, at::Tensor& max_radii);

}  // namespace gaps::backend

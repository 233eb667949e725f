#pragma once
// The SSIM map's two passes, and the training loss built on them, as plain tensor functions, one implementation per
// device (cpu/ssim.cpp, cuda/ssim.cu), with the maths of ssim_math.h. losses.cpp wraps them as autograd functions
// through backend.h's table; nothing else should call them.
#include <ATen/Tensor.h>

namespace gaps::backend {

struct SsimForward {
  at::Tensor map;       // H x W x C
  at::Tensor partials;  // H x W x C x 3: dS/dmu_x, dS/dE[x^2], dS/dE[xy]
};

// pred and gt: contiguous H x W x C of one floating dtype and device.
SsimForward ssim_forward_cpu(const at::Tensor& pred, const at::Tensor& gt);
// dL/dpred for dL/dmap = g_map.
at::Tensor ssim_backward_cpu(const at::Tensor& pred, const at::Tensor& gt, const at::Tensor& partials,
                             const at::Tensor& g_map);

// The training loss (1 - lambda) * mean(w * |pred - gt|) + lambda * mean(w * (1 - SSIM map)), w = 1 where `weight` is
// undefined, else H x W x 1.
struct PhotometricForward {
  at::Tensor loss;      // 0-dim
  at::Tensor partials;  // as SsimForward::partials, for the backward pass
};
// The CPU's is ATen operations over the SSIM passes, in the order autograd differentiated them when the loss was
// written in them (so CPU training keeps its bits); CUDA's is fused: two kernels and a sum each way.
PhotometricForward photometric_forward_cpu(const at::Tensor& pred, const at::Tensor& gt, const at::Tensor& weight,
                                           double lambda);
// dL/dpred for dL/dloss = g_loss (0-dim, on pred's device).
at::Tensor photometric_backward_cpu(const at::Tensor& pred, const at::Tensor& gt, const at::Tensor& partials,
                                    const at::Tensor& weight, double lambda, const at::Tensor& g_loss);

#if defined(GAPS_CUDA_KERNELS)
PhotometricForward photometric_forward_cuda(const at::Tensor& pred, const at::Tensor& gt, const at::Tensor& weight,
                                            double lambda);
at::Tensor photometric_backward_cuda(const at::Tensor& pred, const at::Tensor& gt, const at::Tensor& partials,
                                     const at::Tensor& weight, double lambda, const at::Tensor& g_loss);
SsimForward ssim_forward_cuda(const at::Tensor& pred, const at::Tensor& gt);
at::Tensor ssim_backward_cuda(const at::Tensor& pred, const at::Tensor& gt, const at::Tensor& partials,
                              const at::Tensor& g_map);
#endif

}  // namespace gaps::backend

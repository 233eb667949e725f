#pragma once
// The SSIM map's two passes as plain tensor functions, one implementation per device (cpu/ssim.cpp,
// cuda/ssim.cu), with the maths of ssim_math.h. losses.cpp wraps them as an autograd function through
// backend.h's table; nothing else should call them.
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

#if defined(GAPS_CUDA_KERNELS)
SsimForward ssim_forward_cuda(const at::Tensor& pred, const at::Tensor& gt);
at::Tensor ssim_backward_cuda(const at::Tensor& pred, const at::Tensor& gt, const at::Tensor& partials,
                              const at::Tensor& g_map);
#endif

}  // namespace gaps::backend

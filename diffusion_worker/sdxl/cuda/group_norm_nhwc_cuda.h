#pragma once
// GroupNorm (and the SiLU that follows it in every ResNet block) over channels-last activations on the GPU.
// ATen's CUDA GroupNorm makes its input contiguous and returns NCHW, so a UNet whose convolutions run
// channels-last (NHWC, cuDNN's native layout for half-precision tensor cores) would pay two layout
// transposes at every normalisation; this keeps the layout and folds the activation into the same pass.
// Forward only (inference): layers.cpp uses ATen's where autograd needs the graph. Only builds with CUDA
// kernels (GAPS_CUDA_KERNELS) define it.
#include <ATen/Tensor.h>

namespace gaps::sdxl {

// x: N x C x H x W, contiguous in channels-last order, float32, float16 or bfloat16 on a CUDA device;
// weight, bias: C values on that device. Returns weight * (x - mean) / sqrt(var + eps) + bias per group of
// C / groups channels (biased variance, as at::group_norm), passed through SiLU when `silu`, in x's type and
// layout. Moments accumulate in float32 about a per-group shift (the group's first value), so large offsets
// do not cancel, and in a fixed order: the same input gives the same bits. Up to 4096 channels (a block keeps
// per-channel sums in shared memory; more is refused).
at::Tensor group_norm_nhwc_cuda(const at::Tensor& x, int64_t groups, const at::Tensor& weight, const at::Tensor& bias,
                                double eps, bool silu);

}  // namespace gaps::sdxl

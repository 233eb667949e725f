#pragma once
// Image losses for training, differentiable through autograd (with respect to the prediction).
//
// Images are HxWxC tensors (C = 3 for RGB) with values nominally in [0, 1], float32 or float64, on
// any device; `pred` and `gt` must match in shape, dtype and device. Shape mismatches are
// programming errors and throw c10::Error (TORCH_CHECK), like any ATen op in the training loop.
// Call these qualified (gaps::l1_loss): argument-dependent lookup also finds at::l1_loss.
#include <ATen/Tensor.h>

namespace gaps {

// Mean absolute error over all pixels and channels.
at::Tensor l1_loss(const at::Tensor& pred, const at::Tensor& gt);

// Per-pixel SSIM as in the original 3D Gaussian Splatting `ssim()`: 11x11 Gaussian window
// (sigma 1.5), per-channel filtering with zero padding of 5 (so the map has the image size),
// C1 = 0.01^2, C2 = 0.03^2. Returns HxWxC, same layout as the inputs.
at::Tensor ssim_map(const at::Tensor& pred, const at::Tensor& gt);

// Mean of ssim_map (scalar tensor).
at::Tensor ssim(const at::Tensor& pred, const at::Tensor& gt);

// The 3DGS photometric loss (1 - lambda) * L1 + lambda * (1 - SSIM).
at::Tensor photometric_loss(const at::Tensor& pred, const at::Tensor& gt, double lambda = 0.2);

// Per-pixel weighted variant (e.g. confidence-weighted pseudo views); `weight` is HxW, broadcast
// over channels:  (1 - lambda) * mean(w * |pred - gt|) + lambda * mean(w * (1 - ssim_map)). With w
// == 1 it equals photometric_loss.
at::Tensor weighted_photometric_loss(const at::Tensor& pred, const at::Tensor& gt, const at::Tensor& weight,
                                     double lambda = 0.2);

}  // namespace gaps

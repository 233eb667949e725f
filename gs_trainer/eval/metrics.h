#pragma once
// Evaluation metrics for rendered test views (no autograd). Images are HxWx3 tensors in [0, 1] on
// any device; values are clamped to [0, 1] before measuring, as renders are when saved.
#include <ATen/Tensor.h>

#include <optional>
#include <vector>

#include "absl/status/statusor.h"

namespace gaps {

class Lpips;

struct ImageMetrics {
  double psnr = 0.0;
  double ssim = 0.0;
  std::optional<double> lpips;  // absent when no LPIPS backbone is available
};

// 10 log10(1 / MSE), MSE over all pixels and channels (computed in float64); +inf for equal images.
double psnr(const at::Tensor& pred, const at::Tensor& gt);

// Mean SSIM with the 3DGS window (see losses.h ssim_map).
double ssim_metric(const at::Tensor& pred, const at::Tensor& gt);

// PSNR and SSIM, plus LPIPS when `lpips` is given.
ImageMetrics evaluate_image(const at::Tensor& pred, const at::Tensor& gt, const Lpips* lpips = nullptr);

// Per-view average (the papers average per-image PSNR, not the PSNR of the pooled MSE). LPIPS is
// averaged when every view has it. Errors: no views; LPIPS present for some views only (that means
// a caller bug, and a silently partial average would be misleading).
absl::StatusOr<ImageMetrics> average_metrics(const std::vector<ImageMetrics>& views);

}  // namespace gaps

#include "diffusion_worker/depth_control.h"

#include <ATen/ATen.h>
#include "absl/strings/str_cat.h"

namespace gaps {

absl::StatusOr<DepthControl> depth_control_image(const at::Tensor& depth, const at::Tensor& alpha,
                                                 const DepthControlOptions& o) {
  if (!depth.defined() || !alpha.defined() || depth.dim() != 2 || depth.sizes() != alpha.sizes()) {
    return absl::InvalidArgumentError("depth control: depth and alpha must be H x W maps of one size");
  }
  if (o.variance_window < 1 || o.variance_window % 2 == 0 || !(o.max_relative_variance >= 0) || !(o.min_alpha > 0)) {
    return absl::InvalidArgumentError(absl::StrCat("depth control: variance_window must be odd and >= 1 (got ",
                                                   o.variance_window,
                                                   "), max_relative_variance >= 0 and min_alpha > 0"));
  }
  // Double precision: the variance is a difference of nearly equal means.
  const at::Tensor a = alpha.to(at::kCPU, at::kDouble);
  const at::Tensor d = depth.to(at::kCPU, at::kDouble) / a.clamp_min(1e-12);
  const at::Tensor covered = (a >= o.min_alpha) & (d > 0) & d.isfinite();
  const at::Tensor m = covered.to(at::kDouble);
  const at::Tensor dc = at::where(covered, d, at::zeros_like(d));
  // Window sums as means over the same (zero-padded) window: their ratios are the covered pixels' means.
  const auto window_mean = [&](const at::Tensor& x) {
    return at::avg_pool2d(x.unsqueeze(0).unsqueeze(0), {o.variance_window, o.variance_window}, {1, 1},
                          {o.variance_window / 2, o.variance_window / 2})
        .squeeze(0)
        .squeeze(0);
  };
  const at::Tensor count = window_mean(m).clamp_min(1e-300);
  const at::Tensor mean = window_mean(dc) / count;
  const at::Tensor mean_sq = window_mean(dc * dc) / count;
  const at::Tensor relative_variance = ((mean_sq - mean * mean) / (mean * mean)).clamp_min(0);
  const at::Tensor reliable = covered & (relative_variance <= o.max_relative_variance);

  at::Tensor value = at::zeros_like(d);
  if (reliable.any().item<bool>()) {
    const at::Tensor inverse = 1.0 / at::where(reliable, d, at::ones_like(d));
    const at::Tensor reliable_inverse = inverse.masked_select(reliable);
    const double lo = reliable_inverse.min().item<double>(), hi = reliable_inverse.max().item<double>();
    const at::Tensor normalised = hi > lo ? (inverse - lo) / (hi - lo) : at::ones_like(inverse);
    value = at::where(reliable, normalised, value);
  }
  return DepthControl{value.to(at::kFloat).unsqueeze(0).expand({3, -1, -1}).contiguous(), reliable};
}

absl::StatusOr<DepthControl> disparity_control_image(const at::Tensor& disparity) {
  if (!disparity.defined() || disparity.dim() != 2) {
    return absl::InvalidArgumentError("disparity control: the disparity must be an H x W map");
  }
  const at::Tensor d = disparity.to(at::kCPU, at::kDouble);
  if (!d.isfinite().all().item<bool>()) return absl::InvalidArgumentError("disparity control: non-finite disparity");
  const double lo = d.min().item<double>(), hi = d.max().item<double>();
  const at::Tensor value = hi > lo ? (d - lo) / (hi - lo) : at::ones_like(d);
  return DepthControl{value.to(at::kFloat).unsqueeze(0).expand({3, -1, -1}).contiguous(),
                      at::ones(d.sizes(), at::kBool)};
}

}  // namespace gaps

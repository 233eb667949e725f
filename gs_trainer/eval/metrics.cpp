#include "gs_trainer/eval/metrics.h"

#include <ATen/ATen.h>
#include <ATen/core/grad_mode.h>

#include <cmath>
#include <limits>

#include "absl/status/status.h"
#include "absl/strings/str_cat.h"
#include "gs_trainer/eval/lpips.h"
#include "gs_trainer/raster/losses.h"

namespace gaps {
namespace {

at::Tensor clamp01(const at::Tensor& image) { return image.clamp(0.0, 1.0); }

}  // namespace

double psnr(const at::Tensor& pred, const at::Tensor& gt) {
  at::NoGradGuard no_grad;
  TORCH_CHECK(pred.sizes() == gt.sizes(), "PSNR inputs differ in shape: ", pred.sizes(), " vs ", gt.sizes());
  // float64 so that the MSE of near-identical images is not dominated by rounding.
  at::Tensor diff = clamp01(pred).to(at::kDouble) - clamp01(gt).to(at::kDouble);
  const double mse = diff.pow(2).mean().item<double>();
  if (mse == 0.0) return std::numeric_limits<double>::infinity();
  return 10.0 * std::log10(1.0 / mse);
}

double ssim_metric(const at::Tensor& pred, const at::Tensor& gt) {
  at::NoGradGuard no_grad;
  return gaps::ssim(clamp01(pred), clamp01(gt)).item<double>();
}

ImageMetrics evaluate_image(const at::Tensor& pred, const at::Tensor& gt, const Lpips* lpips) {
  at::NoGradGuard no_grad;
  ImageMetrics m;
  m.psnr = psnr(pred, gt);
  m.ssim = ssim_metric(pred, gt);
  if (lpips != nullptr) m.lpips = lpips->distance(clamp01(pred), clamp01(gt)).item<double>();
  return m;
}

absl::StatusOr<ImageMetrics> average_metrics(const std::vector<ImageMetrics>& views) {
  if (views.empty()) return absl::InvalidArgumentError("average_metrics: no views to average");
  const bool with_lpips = views.front().lpips.has_value();
  ImageMetrics mean;
  double lpips_sum = 0.0;
  for (size_t i = 0; i < views.size(); ++i) {
    if (views[i].lpips.has_value() != with_lpips) {
      return absl::InvalidArgumentError(
          absl::StrCat("average_metrics: view ", i, (with_lpips ? " lacks" : " has"), " an LPIPS value unlike view 0"));
    }
    mean.psnr += views[i].psnr;
    mean.ssim += views[i].ssim;
    if (with_lpips) lpips_sum += *views[i].lpips;
  }
  const double n = static_cast<double>(views.size());
  mean.psnr /= n;
  mean.ssim /= n;
  if (with_lpips) mean.lpips = lpips_sum / n;
  return mean;
}

}  // namespace gaps

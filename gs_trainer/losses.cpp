#include "gs_trainer/losses.h"

#include <ATen/ATen.h>

namespace gaps {
namespace {

constexpr int64_t kWindow = 11;
constexpr double kSigma = 1.5;
constexpr double kC1 = 0.01 * 0.01;
constexpr double kC2 = 0.03 * 0.03;

void check_pair(const at::Tensor& pred, const at::Tensor& gt) {
  TORCH_CHECK(pred.dim() == 3, "expected an HxWxC image, got shape ", pred.sizes());
  TORCH_CHECK(pred.sizes() == gt.sizes(), "prediction ", pred.sizes(), " and ground truth ",
              gt.sizes(), " differ in shape");
}

// Normalised 1-D Gaussian, built on the target device so the hot path never copies from the host.
at::Tensor gaussian_1d(const at::TensorOptions& options) {
  at::Tensor x = at::arange(kWindow, options) - static_cast<double>(kWindow / 2);
  at::Tensor g = at::exp(-(x * x) / (2.0 * kSigma * kSigma));
  return g / g.sum();
}

// Depthwise Gaussian blur of a 1xKxHxW stack with zero padding. The 2-D window of 3DGS is the outer
// product of the 1-D one, so two 1-D passes give the same result with 22 instead of 121 taps.
at::Tensor blur(const at::Tensor& x) {
  const int64_t k = x.size(1);
  at::Tensor g = gaussian_1d(x.options());
  at::Tensor horizontal = g.view({1, 1, 1, kWindow}).expand({k, 1, 1, kWindow}).contiguous();
  at::Tensor vertical = g.view({1, 1, kWindow, 1}).expand({k, 1, kWindow, 1}).contiguous();
  const int64_t pad = kWindow / 2;
  const std::vector<int64_t> ones = {1, 1};
  const std::vector<int64_t> pad_w = {0, pad};
  const std::vector<int64_t> pad_h = {pad, 0};
  at::Tensor y = at::conv2d(x, horizontal, at::Tensor(), ones, pad_w, ones, k);
  return at::conv2d(y, vertical, at::Tensor(), ones, pad_h, ones, k);
}

}  // namespace

at::Tensor l1_loss(const at::Tensor& pred, const at::Tensor& gt) {
  check_pair(pred, gt);
  return (pred - gt).abs().mean();
}

at::Tensor ssim_map(const at::Tensor& pred, const at::Tensor& gt) {
  check_pair(pred, gt);
  const int64_t c = pred.size(2);
  // 1xCxHxW planes; the five blurred quantities go through one depthwise convolution.
  at::Tensor x = pred.permute({2, 0, 1}).unsqueeze(0);
  at::Tensor y = gt.permute({2, 0, 1}).unsqueeze(0);
  std::vector<at::Tensor> moments = blur(at::cat({x, y, x * x, y * y, x * y}, 1)).split(c, 1);
  const at::Tensor& mu_x = moments[0];
  const at::Tensor& mu_y = moments[1];
  at::Tensor mu_xx = mu_x * mu_x;
  at::Tensor mu_yy = mu_y * mu_y;
  at::Tensor mu_xy = mu_x * mu_y;
  at::Tensor var_x = moments[2] - mu_xx;
  at::Tensor var_y = moments[3] - mu_yy;
  at::Tensor cov_xy = moments[4] - mu_xy;
  at::Tensor map =
      ((2 * mu_xy + kC1) * (2 * cov_xy + kC2)) / ((mu_xx + mu_yy + kC1) * (var_x + var_y + kC2));
  return map.squeeze(0).permute({1, 2, 0});
}

at::Tensor ssim(const at::Tensor& pred, const at::Tensor& gt) {
  return gaps::ssim_map(pred, gt).mean();
}

at::Tensor photometric_loss(const at::Tensor& pred, const at::Tensor& gt, double lambda) {
  // Qualified: argument-dependent lookup would also find at::l1_loss.
  return (1.0 - lambda) * gaps::l1_loss(pred, gt) + lambda * (1.0 - gaps::ssim(pred, gt));
}

at::Tensor weighted_photometric_loss(const at::Tensor& pred, const at::Tensor& gt,
                                     const at::Tensor& weight, double lambda) {
  check_pair(pred, gt);
  TORCH_CHECK(weight.dim() == 2 && weight.size(0) == pred.size(0) && weight.size(1) == pred.size(1),
              "weight must be HxW = ", pred.size(0), "x", pred.size(1), ", got ", weight.sizes());
  at::Tensor w = weight.unsqueeze(2);  // broadcast over channels
  at::Tensor l1 = (w * (pred - gt).abs()).mean();
  at::Tensor dssim = (w * (1.0 - gaps::ssim_map(pred, gt))).mean();
  return (1.0 - lambda) * l1 + lambda * dssim;
}

}  // namespace gaps

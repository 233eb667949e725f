#include "gs_trainer/raster/losses.h"

#include <ATen/ATen.h>
#include <torch/csrc/autograd/custom_function.h>

#include "gs_trainer/raster/backend.h"

namespace gaps {
namespace {

using torch::autograd::AutogradContext;
using torch::autograd::tensor_list;
using torch::autograd::Variable;

void check_pair(const at::Tensor& pred, const at::Tensor& gt) {
  TORCH_CHECK(pred.dim() == 3, "expected an HxWxC image, got shape ", pred.sizes());
  TORCH_CHECK(pred.sizes() == gt.sizes(), "prediction ", pred.sizes(), " and ground truth ", gt.sizes(),
              " differ in shape");
}

// The map is differentiated with respect to the prediction only: the target of a loss is data.
class SsimMapFunction : public torch::autograd::Function<SsimMapFunction> {
 public:
  static tensor_list forward(AutogradContext* ctx, Variable pred, Variable gt) {
    const backend::SsimForward f = backend::raster_backend(pred.device()).ssim_forward(pred, gt);
    ctx->save_for_backward({pred, gt, f.partials});
    return {f.map};
  }

  static tensor_list backward(AutogradContext* ctx, tensor_list grads) {
    const auto s = ctx->get_saved_variables();
    return {backend::raster_backend(s[0].device()).ssim_backward(s[0], s[1], s[2], grads[0]), Variable()};
  }
};

}  // namespace

at::Tensor l1_loss(const at::Tensor& pred, const at::Tensor& gt) {
  check_pair(pred, gt);
  return (pred - gt).abs().mean();
}

at::Tensor ssim_map(const at::Tensor& pred, const at::Tensor& gt) {
  check_pair(pred, gt);
  TORCH_CHECK(pred.scalar_type() == gt.scalar_type() && pred.device() == gt.device(),
              "prediction and ground truth must share dtype and device");
  TORCH_CHECK(!gt.requires_grad(), "ssim_map differentiates the prediction only; detach the ground truth");
  return SsimMapFunction::apply(pred, gt)[0];
}

at::Tensor ssim(const at::Tensor& pred, const at::Tensor& gt) { return gaps::ssim_map(pred, gt).mean(); }

at::Tensor photometric_loss(const at::Tensor& pred, const at::Tensor& gt, double lambda) {
  // Qualified: argument-dependent lookup would also find at::l1_loss.
  return (1.0 - lambda) * gaps::l1_loss(pred, gt) + lambda * (1.0 - gaps::ssim(pred, gt));
}

at::Tensor weighted_photometric_loss(const at::Tensor& pred, const at::Tensor& gt, const at::Tensor& weight,
                                     double lambda) {
  check_pair(pred, gt);
  TORCH_CHECK(weight.dim() == 2 && weight.size(0) == pred.size(0) && weight.size(1) == pred.size(1),
              "weight must be HxW = ", pred.size(0), "x", pred.size(1), ", got ", weight.sizes());
  at::Tensor w = weight.unsqueeze(2);  // broadcast over channels
  at::Tensor l1 = (w * (pred - gt).abs()).mean();
  at::Tensor dssim = (w * (1.0 - gaps::ssim_map(pred, gt))).mean();
  return (1.0 - lambda) * l1 + lambda * dssim;
}

}  // namespace gaps

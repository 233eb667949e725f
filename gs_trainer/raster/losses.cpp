#include "gs_trainer/raster/losses.h"

#include <optional>

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

// The SSIM kernels' inputs: one dtype and device, and a ground truth that is data.
void check_differentiable_pair(const at::Tensor& pred, const at::Tensor& gt, const char* what) {
  check_pair(pred, gt);
  TORCH_CHECK(pred.scalar_type() == gt.scalar_type() && pred.device() == gt.device(),
              "prediction and ground truth must share dtype and device");
  TORCH_CHECK(!gt.requires_grad(), what, " differentiates the prediction only; detach the ground truth");
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

// The training loss (1 - lambda) * mean(w * |pred - gt|) + lambda * mean(w * (1 - SSIM map)) as one autograd node
// (w = 1 when `weight` is undefined; otherwise H x W x 1). Every training step runs it: written with ATen ops it was
// a dozen autograd nodes whose bookkeeping on the host cost more than their kernels. The gradient is formed with the
// float operations autograd used for those ops, in the same order, so training results keep their bits.
class PhotometricLossFunction : public torch::autograd::Function<PhotometricLossFunction> {
 public:
  static tensor_list forward(AutogradContext* ctx, Variable pred, Variable gt, std::optional<at::Tensor> weight_in,
                             double lambda) {
    const at::Tensor weight = weight_in.value_or(at::Tensor());
    const backend::SsimForward f = backend::raster_backend(pred.device()).ssim_forward(pred, gt);
    const at::Tensor diff = pred - gt;
    at::Tensor loss;
    if (weight.defined()) {
      loss = (1.0 - lambda) * (weight * diff.abs()).mean() + lambda * (weight * (1.0 - f.map)).mean();
    } else {
      loss = (1.0 - lambda) * diff.abs().mean() + lambda * (1.0 - f.map.mean());
    }
    ctx->save_for_backward({pred, gt, f.partials, diff});
    ctx->saved_data["lambda"] = lambda;
    // The weight is data, not an input of the graph: it travels outside the saved variables.
    if (weight.defined()) ctx->saved_data["weight"] = weight;
    return {loss};
  }

  static tensor_list backward(AutogradContext* ctx, tensor_list grads) {
    const auto s = ctx->get_saved_variables();
    const at::Tensor &pred = s[0], &diff = s[3];
    const at::Tensor weight = ctx->saved_data.count("weight") ? ctx->saved_data["weight"].toTensor() : at::Tensor();
    const double lambda = ctx->saved_data["lambda"].toDouble();
    const int64_t n = pred.numel();
    // As autograd: the scalar factors, then the mean's division, then the weight, then |.|'s sign.
    at::Tensor g_l1 = ((grads[0] * (1.0 - lambda)) / n).expand(pred.sizes());
    at::Tensor g_map = ((grads[0] * lambda) / n).expand(pred.sizes());
    if (weight.defined()) {
      g_l1 = g_l1 * weight;
      g_map = g_map * weight;
    }
    g_map = g_map.neg().contiguous();
    const at::Tensor g_ssim = backend::raster_backend(pred.device()).ssim_backward(pred, s[1], s[2], g_map);
    return {g_ssim + g_l1 * diff.sgn(), Variable(), Variable(), Variable()};
  }
};

}  // namespace

at::Tensor l1_loss(const at::Tensor& pred, const at::Tensor& gt) {
  check_pair(pred, gt);
  return (pred - gt).abs().mean();
}

at::Tensor ssim_map(const at::Tensor& pred, const at::Tensor& gt) {
  check_differentiable_pair(pred, gt, "ssim_map");
  return SsimMapFunction::apply(pred, gt)[0];
}

at::Tensor ssim(const at::Tensor& pred, const at::Tensor& gt) { return gaps::ssim_map(pred, gt).mean(); }

at::Tensor photometric_loss(const at::Tensor& pred, const at::Tensor& gt, double lambda) {
  check_differentiable_pair(pred, gt, "photometric_loss");
  return PhotometricLossFunction::apply(pred, gt, std::nullopt, lambda)[0];
}

at::Tensor weighted_photometric_loss(const at::Tensor& pred, const at::Tensor& gt, const at::Tensor& weight,
                                     double lambda) {
  check_differentiable_pair(pred, gt, "weighted_photometric_loss");
  TORCH_CHECK(weight.dim() == 2 && weight.size(0) == pred.size(0) && weight.size(1) == pred.size(1),
              "weight must be HxW = ", pred.size(0), "x", pred.size(1), ", got ", weight.sizes());
  TORCH_CHECK(!weight.requires_grad(),
              "weighted_photometric_loss differentiates the prediction only; detach the weight");
  return PhotometricLossFunction::apply(pred, gt, std::optional<at::Tensor>(weight.unsqueeze(2)),
                                        lambda)[0];  // the weight spans the channels
}

}  // namespace gaps

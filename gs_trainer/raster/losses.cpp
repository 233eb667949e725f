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

// The training loss (backend::photometric_forward) as one autograd node, w = 1 when `weight` is undefined, otherwise
// H x W x 1. Every training step runs it: written with ATen ops it was a dozen autograd nodes whose bookkeeping on
// the host cost more than their kernels.
class PhotometricLossFunction : public torch::autograd::Function<PhotometricLossFunction> {
 public:
  static tensor_list forward(AutogradContext* ctx, Variable pred, Variable gt, std::optional<at::Tensor> weight_in,
                             double lambda) {
    const at::Tensor weight = weight_in.value_or(at::Tensor());
    const backend::PhotometricForward f =
        backend::raster_backend(pred.device()).photometric_forward(pred, gt, weight, lambda);
    ctx->save_for_backward({pred, gt, f.partials});
    ctx->saved_data["lambda"] = lambda;
    // The weight is data, not an input of the graph: it travels outside the saved variables.
    if (weight.defined()) ctx->saved_data["weight"] = weight;
    return {f.loss};
  }

  static tensor_list backward(AutogradContext* ctx, tensor_list grads) {
    const auto s = ctx->get_saved_variables();
    const at::Tensor weight = ctx->saved_data.count("weight") ? ctx->saved_data["weight"].toTensor() : at::Tensor();
    const double lambda = ctx->saved_data["lambda"].toDouble();
    const at::Tensor g_pred =
        backend::raster_backend(s[0].device()).photometric_backward(s[0], s[1], s[2], weight, lambda, grads[0]);
    return {g_pred, Variable(), Variable(), Variable()};
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

#include "gs_trainer/train/adam.h"

#include <algorithm>
#include <cmath>

#include <ATen/ATen.h>
#include <ATen/core/grad_mode.h>

#include "gs_trainer/train/cuda/adam_cuda.h"

namespace gaps {
namespace {

// The update in ATen operations, for any device.
void adam_update_aten(at::Tensor& param, const at::Tensor& grad, at::Tensor& exp_avg, at::Tensor& exp_avg_sq,
                      const backend::AdamStep& step) {
  exp_avg.mul_(step.beta1).add_(grad, 1 - step.beta1);
  exp_avg_sq.mul_(step.beta2).addcmul_(grad, grad, 1 - step.beta2);
  const at::Tensor denom = (exp_avg_sq.sqrt() / std::sqrt(step.bias_correction2)).add_(step.eps);
  param.addcdiv_(exp_avg, denom, -step.lr / step.bias_correction1);
}

// Whether the fused kernel takes this update: a build with it, CUDA tensors and a gradient it can read as one
// dense array. ATen's operations take the rest.
bool fused_update_takes([[maybe_unused]] const at::Tensor& param, [[maybe_unused]] const at::Tensor& grad) {
#if defined(GAPS_CUDA_KERNELS)
  return param.is_cuda() && grad.is_contiguous();
#else
  return false;
#endif
}

}  // namespace

GaussianAdam::GaussianAdam(GaussianModel& model, std::vector<double> learning_rates, double eps, double beta1,
                           double beta2)
    : model_(model), eps_(eps), beta1_(beta1), beta2_(beta2) {
  const auto params = model.parameters();
  TORCH_CHECK(learning_rates.size() == params.size(), "one learning rate per parameter tensor expected");
  for (size_t i = 0; i < params.size(); ++i) {
    *params[i] = params[i]->detach().requires_grad_(true);
    groups_.push_back({params[i], learning_rates[i], at::zeros_like(*params[i]), at::zeros_like(*params[i])});
  }
}

void GaussianAdam::step() {
  ++steps_;
  const double bc1 = 1 - std::pow(beta1_, static_cast<double>(steps_));
  const double bc2 = 1 - std::pow(beta2_, static_cast<double>(steps_));
  at::AutoGradMode no_grad(false);
  std::vector<backend::AdamTensors> fused;
  for (auto& g : groups_) {
    const at::Tensor& grad = g.param->grad();
    if (!grad.defined()) continue;
    at::Tensor param = g.param->detach();  // shares storage: the update is in place
    const backend::AdamStep constants{g.lr, beta1_, beta2_, eps_, bc1, bc2};
    if (fused_update_takes(param, grad))
      fused.push_back({param, grad, g.exp_avg, g.exp_avg_sq, constants});
    else
      adam_update_aten(param, grad, g.exp_avg, g.exp_avg_sq, constants);
  }
#if defined(GAPS_CUDA_KERNELS)
  backend::adam_update_cuda(fused);
#endif
}

void GaussianAdam::zero_grad() {
  for (auto& g : groups_)
    if (g.param->grad().defined()) g.param->mutable_grad() = at::Tensor();
}

void GaussianAdam::keep_rows(const at::Tensor& keep) {
  const at::Tensor idx = keep.nonzero().squeeze(1);
  for (auto& g : groups_) {
    *g.param = g.param->detach().index_select(0, idx).requires_grad_(true);
    g.exp_avg = g.exp_avg.index_select(0, idx);
    g.exp_avg_sq = g.exp_avg_sq.index_select(0, idx);
  }
}

void GaussianAdam::append_rows(const GaussianModel& extra) {
  auto extra_params = const_cast<GaussianModel&>(extra).parameters();
  for (size_t i = 0; i < groups_.size(); ++i) {
    auto& g = groups_[i];
    const at::Tensor add = extra_params[i]->detach().to(g.param->options().requires_grad(false));
    *g.param = at::cat({g.param->detach(), add}).requires_grad_(true);
    g.exp_avg = at::cat({g.exp_avg, at::zeros_like(add)});
    g.exp_avg_sq = at::cat({g.exp_avg_sq, at::zeros_like(add)});
  }
}

void GaussianAdam::reset_state(size_t index) {
  groups_[index].exp_avg.zero_();
  groups_[index].exp_avg_sq.zero_();
}

double exponential_lr(int64_t step, double lr_init, double lr_final, int64_t max_steps) {
  if (lr_init <= 0 && lr_final <= 0) return 0.0;
  const double t = std::clamp(static_cast<double>(step) / std::max<int64_t>(max_steps, 1), 0.0, 1.0);
  return std::exp(std::log(lr_init) * (1 - t) + std::log(lr_final) * t);
}

}  // namespace gaps

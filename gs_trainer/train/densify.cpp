#include "gs_trainer/train/densify.h"

#include <cmath>

#include <ATen/ATen.h>
#include <ATen/core/grad_mode.h>

#include "gs_trainer/train/cuda/densify_stats_cuda.h"

namespace gaps {
namespace {

constexpr size_t kOpacityParam = 3;  // index in GaussianModel::parameters()

GaussianModel select_rows(GaussianModel& model, const at::Tensor& idx) {
  GaussianModel out;
  out.max_sh_degree = model.max_sh_degree;
  auto src = model.parameters();
  auto dst = out.parameters();
  for (size_t i = 0; i < src.size(); ++i) *dst[i] = src[i]->detach().index_select(0, idx);
  return out;
}

// Each selected Gaussian becomes `samples` Gaussians drawn from itself, shrunk by 1/(0.8 * samples).
GaussianModel split_copies(GaussianModel& model, const at::Tensor& idx, int samples) {
  GaussianModel parent = select_rows(model, idx);
  GaussianModel child;
  child.max_sh_degree = model.max_sh_degree;
  auto pp = parent.parameters();
  auto cp = child.parameters();
  for (size_t i = 0; i < pp.size(); ++i) *cp[i] = pp[i]->repeat_interleave(samples, 0);
  const at::Tensor stds = at::exp(child.log_scales);
  const at::Tensor local = at::normal(at::zeros_like(stds), stds);
  const at::Tensor q = child.quats / child.quats.norm(2, {1}, true);
  const auto w = q.select(1, 0), x = q.select(1, 1), y = q.select(1, 2), z = q.select(1, 3);
  const at::Tensor R = at::stack({1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
                                  2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
                                  2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)},
                                 1)
                           .view({-1, 3, 3});
  child.means = at::bmm(R, local.unsqueeze(2)).squeeze(2) + child.means;
  child.log_scales = child.log_scales - std::log(0.8 * samples);
  return child;
}

// The `room` candidates with the largest gradients (ties: lower index first). Each candidate adds one
// Gaussian (a clone, or a split's net one), so growth then ends exactly at the budget.
at::Tensor within_budget(const at::Tensor& candidates, const at::Tensor& grads, int64_t room) {
  const at::Tensor idx = candidates.nonzero().squeeze(1);
  if (idx.size(0) <= room) return candidates;
  const at::Tensor order =
      std::get<1>(grads.index_select(0, idx).sort(/*stable=*/true, /*dim=*/0, /*descending=*/true));
  at::Tensor kept = at::zeros_like(candidates);
  kept.index_fill_(0, idx.index_select(0, order.narrow(0, 0, room)), true);
  return kept;
}

}  // namespace

void DensityControl::ensure_size(int64_t n, const at::TensorOptions& opts) {
  if (grad_accum_.defined() && grad_accum_.size(0) == n) return;
  grad_accum_ = at::zeros({n}, opts);
  denom_ = at::zeros({n}, opts);
  max_radii_ = at::zeros({n}, opts.dtype(at::kInt));
}

void DensityControl::accumulate(const at::Tensor& means2d_grad, const at::Tensor& means2d_abs_grad,
                                const at::Tensor& radii, int width, int height) {
  ensure_size(radii.size(0), means2d_grad.options());
  const at::Tensor& g = config_.absolute_gradient && means2d_abs_grad.defined() ? means2d_abs_grad : means2d_grad;
#if defined(GAPS_CUDA_KERNELS)
  if (g.is_cuda() && g.scalar_type() == at::kFloat) {
    backend::accumulate_view_gradients_cuda(g, radii, width, height, grad_accum_, denom_, max_radii_);
    return;
  }
#endif
  // Every step runs this until densification ends, so it is kept to few kernels; radii are 0 exactly where a
  // Gaussian is not visible, which makes them their own mask for the maximum.
  const at::Tensor visible = radii > 0;
  const at::Tensor norm = at::hypot(g.select(1, 0) * (0.5 * width), g.select(1, 1) * (0.5 * height));
  grad_accum_.add_(at::where(visible, norm, 0.0));
  denom_.add_(visible);
  max_radii_ = at::maximum(max_radii_, radii);
}

int64_t DensityControl::densify_and_prune(GaussianModel& model, GaussianAdam& adam, int iteration, uint64_t seed) {
  at::AutoGradMode no_grad(false);
  ensure_size(model.size(), model.means.options());
  const at::Tensor grads = at::nan_to_num(grad_accum_ / denom_, 0.0, 0.0, 0.0);
  const double size_limit = config_.percent_dense * extent_;
  const bool may_grow = config_.max_gaussians <= 0 || model.size() < config_.max_gaussians;
  // Screen-space radii follow the rows through growth (new Gaussians start unseen, at 0).
  at::Tensor radii = max_radii_;
  if (may_grow) {
    at::manual_seed(seed);
    at::Tensor high = grads >= config_.densify_grad_threshold;
    if (config_.max_gaussians > 0) high = within_budget(high, grads, config_.max_gaussians - model.size());
    const at::Tensor max_scale = std::get<0>(at::exp(model.log_scales.detach()).max(1));
    const at::Tensor clone_idx = (high & (max_scale <= size_limit)).nonzero().squeeze(1);
    const at::Tensor split_idx = (high & (max_scale > size_limit)).nonzero().squeeze(1);
    GaussianModel clones = select_rows(model, clone_idx);
    GaussianModel splits = split_copies(model, split_idx, 2);
    adam.append_rows(clones);
    adam.append_rows(splits);
    radii = at::cat({radii, at::zeros({clones.size() + splits.size()}, radii.options())});
    // The split parents are replaced by their children.
    at::Tensor keep = at::ones({model.size()}, model.means.options().dtype(at::kBool));
    keep.index_fill_(0, split_idx, false);
    adam.keep_rows(keep);
    radii = radii.index({keep});
  }
  at::Tensor prune = model.opacities().detach() < config_.min_opacity;
  // 3DGS prunes screen- and world-space giants once the first opacity reset has passed; without resets
  // (opacity_reset_interval 0) never, as in the measured configuration.
  if (config_.opacity_reset_interval > 0 && iteration > config_.opacity_reset_interval) {
    const at::Tensor max_scale = std::get<0>(at::exp(model.log_scales.detach()).max(1));
    prune = prune | (radii > config_.max_screen_size) | (max_scale > 0.1 * extent_);
  }
  adam.keep_rows(~prune);
  ensure_size(model.size(), model.means.options());
  grad_accum_.zero_();
  denom_.zero_();
  max_radii_.zero_();
  return model.size();
}

int64_t DensityControl::prune_low_contribution(GaussianModel& model, GaussianAdam& adam,
                                               const at::Tensor& contribution) {
  TORCH_CHECK(contribution.dim() == 1 && contribution.size(0) == model.size(),
              "one contribution per Gaussian expected, got ", contribution.sizes(), " for ", model.size());
  adam.keep_rows(contribution.to(model.means.device()) >= config_.prune_min_contribution);
  grad_accum_ = at::Tensor();
  ensure_size(model.size(), model.means.options());
  return model.size();
}

void DensityControl::reset_opacity(GaussianModel& model, GaussianAdam& adam) {
  at::AutoGradMode no_grad(false);
  const double cap = std::log(0.01 / 0.99);
  model.opacity_logits.clamp_max_(cap);
  adam.reset_state(kOpacityParam);
}

}  // namespace gaps

#include "gs_trainer/train/trainer.h"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <numeric>
#include <random>

#include <ATen/ATen.h>
#include "absl/strings/str_cat.h"
#include "gs_trainer/raster/losses.h"
#include "gs_trainer/train/budget.h"

namespace gaps {

std::vector<double> default_learning_rates(const TrainConfig& c, double extent) {
  // Order of GaussianModel::parameters(): means, log_scales, quats, opacity_logits, sh_dc, sh_rest.
  return {c.position_lr_init * extent, c.scaling_lr, c.rotation_lr, c.opacity_lr, c.feature_lr, c.feature_lr / 20.0};
}

namespace {

TrainConfig with_resolved_budget(TrainConfig config, const std::vector<TrainingView>& views) {
  config.max_gaussians = gaussian_budget(config.max_gaussians, config.gaussians_per_variation, views);
  return config;
}

}  // namespace

Trainer::Trainer(GaussianModel initial, std::vector<TrainingView> views, TrainConfig config)
    : config_(with_resolved_budget(std::move(config), views)),
      views_(std::move(views)),
      model_(std::move(initial)),
      extent_(cameras_extent([&] {
        std::vector<Camera> cams;
        for (const auto& v : views_) cams.push_back(v.camera);
        return cams;
      }())),
      adam_(model_, default_learning_rates(config_, extent_), config_.adam_eps),
      density_(config_, extent_),
      rng_state_(config_.seed) {
  TORCH_CHECK(!views_.empty(), "training needs at least one view");
  // A model made from points starts at degree 0; a loaded model (a full 3DGS PLY) keeps the degree it
  // renders at, so continuing it does not first throw its view-dependent colour away.
  model_.sh_degree = std::clamp(model_.sh_degree, 0, model_.max_sh_degree);
  background_ = at::full({3}, config_.background, model_.means.options());
}

const TrainingView& Trainer::next_view() {
  // Shuffled passes over the views, as 3DGS pops random cameras from a refilled stack.
  if (view_cursor_ == view_order_.size()) {
    view_order_.resize(views_.size());
    std::iota(view_order_.begin(), view_order_.end(), 0);
    std::mt19937_64 rng(rng_state_++);
    std::shuffle(view_order_.begin(), view_order_.end(), rng);
    view_cursor_ = 0;
  }
  return views_[view_order_[view_cursor_++]];
}

void Trainer::update_schedules() {
  adam_.set_learning_rate(0, exponential_lr(iteration_, config_.position_lr_init * extent_,
                                            config_.position_lr_final * extent_, config_.iterations));
  if (iteration_ > 0 && iteration_ % config_.sh_increase_interval == 0)
    model_.sh_degree = std::min(model_.sh_degree + 1, model_.max_sh_degree);
}

at::Tensor Trainer::step(const at::Tensor& opacity_scale) {
  ++iteration_;
  update_schedules();
  const TrainingView& view = next_view();
  RenderOptions options;
  options.background = background_;
  options.opacity_scale = opacity_scale;
  if (iteration_ < config_.densify_until_iter() && config_.absolute_gradient)
    options.means2d_abs_sink = at::zeros({model_.size(), 2}, model_.means.options());
  RenderOutput out = render(model_, view.camera, options);
  out.means2d.retain_grad();
  at::Tensor loss = photometric_loss(out.rgb, view.image, config_.lambda_dssim);
  loss.backward();
  maintain_density(&out, options, &view.camera);
  return loss.detach();
}

at::Tensor Trainer::step_pseudo(const PseudoView& view, const at::Tensor& opacity_scale) {
  ++iteration_;
  update_schedules();
  RenderOptions options;
  options.background = background_;
  options.opacity_scale = opacity_scale;
  const RenderOutput out = render(model_, view.camera, options);
  at::Tensor loss = weighted_photometric_loss(out.rgb, view.image, view.weight, config_.lambda_dssim);
  loss.backward();
  maintain_density(nullptr, options, nullptr);
  return loss.detach();
}

// Densification statistics come from GT renders only, so pseudo-view noise cannot grow the model; the
// schedule (densify every interval, opacity reset) runs on the iteration count either way.
void Trainer::maintain_density(const RenderOutput* gt_render, const RenderOptions& options, const Camera* camera) {
  if (iteration_ < config_.densify_until_iter()) {
    if (gt_render)
      density_.accumulate(gt_render->means2d.grad(), options.means2d_abs_sink, gt_render->radii, camera->width,
                          camera->height);
    if (gt_render && iteration_ > config_.densify_from_iter && iteration_ % config_.densification_interval == 0)
      density_.densify_and_prune(model_, adam_, iteration_, config_.seed + iteration_);
    if (config_.opacity_reset_interval > 0 && iteration_ % config_.opacity_reset_interval == 0)
      DensityControl::reset_opacity(model_, adam_);
  }
  if (iteration_ == config_.densify_until_iter() && config_.prune_min_contribution > 0) prune_low_contribution();
  if (model_.size() > 0 && model_.means.grad().defined()) adam_.step();
  adam_.zero_grad();
}

void Trainer::prune_low_contribution() {
  at::Tensor contribution = at::zeros({model_.size()}, model_.means.options());
  for (const TrainingView& view : views_) contribution += blending_weights(model_, view.camera);
  density_.prune_low_contribution(model_, adam_, contribution);
}

absl::Status Trainer::run(const std::function<void(const TrainProgress&)>& on_progress, int report_every,
                          const StepFunction& next_step) {
  using clock = std::chrono::steady_clock;
  const auto start = clock::now();
  auto last_report = start;
  int last_iteration = iteration_;
  at::Tensor loss_sum = at::zeros({}, model_.means.options());
  while (iteration_ < config_.iterations) {
    if (next_step) {
      auto loss = next_step();
      if (!loss.ok()) return loss.status();
      loss_sum.add_(*loss);
    } else {
      loss_sum.add_(step());
    }
    if (iteration_ % report_every != 0 && iteration_ != config_.iterations) continue;
    const double mean_loss = loss_sum.item<double>() / (iteration_ - last_iteration);
    if (!std::isfinite(mean_loss))
      return absl::InternalError(absl::StrCat("training diverged: non-finite loss by iteration ", iteration_, " (",
                                              model_.size(), " Gaussians)"));
    const auto now = clock::now();
    TrainProgress p;
    p.iteration = iteration_;
    p.iterations = config_.iterations;
    p.loss = mean_loss;
    p.num_gaussians = model_.size();
    p.elapsed_seconds = std::chrono::duration<double>(now - start).count();
    p.iterations_per_second =
        (iteration_ - last_iteration) / std::max(1e-9, std::chrono::duration<double>(now - last_report).count());
    if (on_progress) on_progress(p);
    last_report = now;
    last_iteration = iteration_;
    loss_sum.zero_();
  }
  return absl::OkStatus();
}

}  // namespace gaps

#pragma once
// The vanilla 3DGS optimisation loop: random GT view, render, (1-λ)L1 + λ D-SSIM, Adam, SH degree
// schedule, adaptive density control. Later training variants build on step().
#include <functional>
#include <optional>
#include <vector>

#include <ATen/Tensor.h>
#include "absl/status/statusor.h"
#include "gs_trainer/model/gaussians.h"
#include "gs_trainer/model/render.h"
#include "gs_trainer/scene/camera.h"
#include "gs_trainer/train/adam.h"
#include "gs_trainer/train/densify.h"
#include "gs_trainer/train/train_config.h"

namespace gaps {

struct TrainingView {
  Camera camera;
  at::Tensor image;  // H x W x 3 in [0, 1], on the training device
};

// A generated view admitted for training, with its per-pixel loss weight (eq. pseudo_loss).
struct PseudoView {
  Camera camera;
  at::Tensor image;   // H x W x 3 in [0, 1], on the training device
  at::Tensor weight;  // H x W, on the training device
  int candidate_id = -1;
};

struct TrainProgress {
  int iteration = 0;
  int iterations = 0;
  double loss = 0.0;  // mean over the iterations since the last report
  int64_t num_gaussians = 0;
  double iterations_per_second = 0.0;
  double elapsed_seconds = 0.0;
};

class Trainer {
 public:
  Trainer(GaussianModel initial, std::vector<TrainingView> views, TrainConfig config);

  // One optimisation step on a GT view, with DropGaussian's opacity scale when given (N values);
  // returns the loss tensor (a device scalar, not synchronised).
  at::Tensor step(const at::Tensor& opacity_scale = {});
  // One step on a pseudo-view with its weighted loss; no densification statistics are taken.
  at::Tensor step_pseudo(const PseudoView& view, const at::Tensor& opacity_scale = {});
  int iteration() const { return iteration_; }
  const GaussianModel& model() const { return model_; }
  const TrainConfig& config() const { return config_; }

  // Runs to config.iterations, reporting every `report_every` iterations. `next_step` performs one
  // iteration (default: step()); its error stops the run. A non-finite loss stops the run with an error that
  // names the iteration. Either way the model up to then stays available through model().
  using StepFunction = std::function<absl::StatusOr<at::Tensor>()>;
  absl::Status run(const std::function<void(const TrainProgress&)>& on_progress, int report_every = 10,
                   const StepFunction& next_step = nullptr);

 private:
  friend struct CheckpointAccess;  // gs_trainer/run/checkpoint.cpp saves and restores this state
  void update_schedules();
  const TrainingView& next_view();
  void maintain_density(const RenderOutput* gt_render, const RenderOptions& options, const Camera* camera);

  TrainConfig config_;
  // At the end of densification: drops the Gaussians below config.prune_min_contribution (densify.h).
  void prune_low_contribution();
  std::vector<TrainingView> views_;
  GaussianModel model_;
  double extent_;
  GaussianAdam adam_;
  DensityControl density_;
  at::Tensor background_;
  std::vector<size_t> view_order_;
  size_t view_cursor_ = 0;
  uint64_t rng_state_;
  int iteration_ = 0;
};

std::vector<double> default_learning_rates(const TrainConfig& config, double extent);

}  // namespace gaps

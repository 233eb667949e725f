#pragma once
// Adaptive density control of 3DGS: gradient statistics, clone / split / prune, opacity reset.
#include <ATen/Tensor.h>

#include "gs_trainer/model/gaussians.h"
#include "gs_trainer/train/adam.h"
#include "gs_trainer/train/train_config.h"

namespace gaps {

class DensityControl {
 public:
  DensityControl(const TrainConfig& config, double scene_extent) : config_(config), extent_(scene_extent) {}

  // After backward on a GT view: accumulates the view-space gradient norm of visible Gaussians. The pixel
  // gradient is scaled by (W/2, H/2) to the normalised-device units that 3DGS's threshold refers to.
  void accumulate(const at::Tensor& means2d_grad, const at::Tensor& means2d_abs_grad, const at::Tensor& radii,
                  int width, int height);
  // Clone small / split large high-gradient Gaussians, then prune; resets the statistics.
  // Returns the number of Gaussians after the operation.
  int64_t densify_and_prune(GaussianModel& model, GaussianAdam& adam, int iteration, uint64_t seed);
  // Removes the Gaussians whose `contribution` (N values, e.g. blending weights summed over the training
  // views) is below config.prune_min_contribution; resets the statistics. Returns the number left.
  int64_t prune_low_contribution(GaussianModel& model, GaussianAdam& adam, const at::Tensor& contribution);
  // Clamps every opacity to at most 0.01 and clears its Adam moments.
  static void reset_opacity(GaussianModel& model, GaussianAdam& adam);

 private:
  friend struct CheckpointAccess;  // gs_trainer/run/checkpoint.cpp saves and restores the statistics
  void ensure_size(int64_t n, const at::TensorOptions& opts);
  const TrainConfig& config_;
  double extent_;
  at::Tensor grad_accum_, denom_, max_radii_;
};

}  // namespace gaps

#pragma once
// The "mvs" initialisation's dense stage: PatchMatch stereo (patchmatch.h) on the training views, each view's
// depth range and source views taken from the sparse stage as the plane sweep takes them, then fusion
// (fusion.h).
#include <functional>
#include <vector>

#include <ATen/Tensor.h>
#include "absl/status/statusor.h"
#include "gs_trainer/init/fusion.h"
#include "gs_trainer/init/patchmatch.h"
#include "gs_trainer/init/plane_sweep.h"
#include "gs_trainer/init/sparse.h"
#include "gs_trainer/init/stage_control.h"
#include "gs_trainer/scene/camera.h"

namespace gaps {

struct MvsStats {
  int views_with_sources = 0;  // views PatchMatch estimated depths for (a depth range and a source view)
  double patchmatch_seconds = 0.0;
  FusionStats fusion;
};

struct MvsResult {
  std::vector<ViewDepthNormal> maps;  // at the working resolution (PatchMatchOptions::max_image_side)
  FusedCloud fused;
  MvsStats stats;
};

// `images` at their cameras' sizes, on the device that picks PatchMatch's path (CUDA tensors: the kernels).
// Depth ranges: view_depth_range with `range` (its depth_margin and min_points_for_range); sources:
// select_neighbors, up to patchmatch.max_source_views. Fails on invalid input, when no view has both a depth
// range and a source, or when PatchMatch fails (CANCELLED when `control` stopped it). `control` hears
// PatchMatch's sweeps and then ("fusion", 0 or 1, 1).
absl::StatusOr<MvsResult> patchmatch_reconstruct(const std::vector<Camera>& cameras,
                                                 const std::vector<at::Tensor>& images, const SparseResult& sparse,
                                                 const PatchMatchOptions& patchmatch, const FusionOptions& fusion,
                                                 const DenseOptions& range, const StageControl& control = {});

}  // namespace gaps

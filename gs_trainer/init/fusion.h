#pragma once
// Fusion of per-view depth and normal maps (patchmatch.h) into one point cloud, in the manner of COLMAP's
// stereo_fusion: a pixel's 3D point gathers the pixels of the other views that see the same surface, and
// becomes a point only when enough views agree on it.
#include <cstdint>
#include <vector>

#include <ATen/Tensor.h>
#include "absl/status/statusor.h"
#include "gs_trainer/init/patchmatch.h"
#include "gs_trainer/scene/scene.h"

namespace gaps {

struct FusionOptions {
  // A pixel of another view joins a cluster when it sees the reference pixel's point as follows.
  double max_depth_error = 0.01;       // |its depth - the point's depth in it| / its depth
  double max_reprojection_px = 2.0;    // its own 3D point lands this close to the reference pixel's centre
  double max_normal_error_deg = 10.0;  // angle between its normal and the reference pixel's (world frame)
  // Distinct views a cluster must span to become a point, the reference view included: 2 keeps what at least
  // one other view confirms, which with 3 training views (fern) still keeps surfaces that one view does not
  // see; higher counts suit many views.
  int min_views = 2;
  // At most this many points (voxel-grid averaging above it); 0: no cap. The run's Gaussian budget belongs
  // here: each point becomes one Gaussian (gaussians_from_points) and densification grows the model up to the
  // budget (train/budget.h, "how many Gaussians a scene needs"), so a larger cloud would start training past
  // what the scene needs and leave it nothing to place where the gradients ask for detail.
  int64_t max_points = 0;
  // The initialisation (initializer.h) adds the sparse stage's triangulated points to the fused cloud (then
  // capped at max_points as one cloud). PatchMatch leaves surfaces seen well by no view without depth, where SIFT
  // tracks spanning several views may still place points (bonsai 12 views: PatchMatch's cloud reaches 0.74 of the
  // test views' 16x16 cells, 0.86 with the sparse points; not yet measured in training, so off by default).
  bool add_sparse_points = false;
};

struct FusionStats {
  std::vector<int64_t> depth_pixels;  // valid depths per view
  int64_t clusters = 0;               // clusters started (one per unfused valid pixel visited)
  int64_t fused_points = 0;           // clusters that spanned min_views views: points before the cap
  int64_t points = 0;                 // after the cap
  double voxel_size = 0.0;            // 0 when no cap was needed
  double seconds = 0.0;
};

struct FusedCloud {
  PointCloud points;   // CPU float tensors
  at::Tensor normals;  // N x 3 float, unit, world frame
  FusionStats stats;
};

// OK, or InvalidArgument naming the first option out of its range.
absl::Status validate_fusion_options(const FusionOptions& options);

// Visits the views in order and their pixels in row-major order; an unfused pixel with a depth starts a
// cluster, its 3D point is projected into every other view and that view's pixel there joins when its depth,
// reprojection and normal agree (FusionOptions). A cluster of >= min_views views becomes a point: the mean
// position and colour and the normalised mean normal of its pixels, which are then marked fused and start no
// cluster of their own. Pixels of a cluster that is too small stay free to join or start another.
// Errors: options out of range, a map whose depth, normal or image does not match its camera's size.
absl::StatusOr<FusedCloud> fuse_patchmatch_maps(const std::vector<ViewDepthNormal>& maps,
                                                const FusionOptions& options = {});

}  // namespace gaps

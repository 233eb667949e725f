#pragma once
// Dense point cloud from the N training views with known poses: fronto-parallel plane-sweep stereo per view
// (ZNCC over a small window, winner-take-all with confidence) and a fusion that keeps only the depths other
// views confirm. The role of COLMAP's patch_match_stereo + stereo_fusion in the paper's initialisation.
// Everything is LibTorch tensor code: it runs on the device the images are on.
#include <optional>
#include <utility>
#include <vector>

#include <ATen/Tensor.h>
#include "absl/status/statusor.h"
#include "gs_trainer/init/sparse.h"
#include "gs_trainer/scene/camera.h"
#include "gs_trainer/scene/scene.h"

namespace gaps {

struct DenseOptions {
  int max_image_side = 400;  // views are downsampled to this longest side first (speed; fern -r 8 is 504)
  int num_planes = 96;       // depth hypotheses, uniform in inverse depth
  int window = 7;            // ZNCC window side (odd)
  int max_neighbors = 4;     // source views per reference view
  // Planes warped at once. Larger chunks mean fewer, longer parallel regions, which matters on a busy machine;
  // past 16 they cost memory and no time (docs/benchmarks.md, "Sparse-view initialisation").
  int planes_per_chunk = 16;
  // Depth range: 1%..99% quantiles of the sparse points' depths in the view, widened by this factor.
  double depth_margin = 0.25;
  int min_points_for_range = 10;  // fewer visible sparse points: the camera's near/far instead
  // Winner-take-all acceptance.
  double min_score = 0.5;         // aggregated ZNCC of the best plane
  double min_margin = 0.02;       // best minus the best plane more than 2 planes away (repeated texture)
  double min_texture_std = 0.01;  // grey standard deviation in the reference window (flat regions: no depth)
  // Fusion: a depth survives when >= min_consistent_views other views agree.
  int min_consistent_views = 1;
  double max_relative_depth_diff = 0.01;
  double max_reprojection_px = 1.0;  // at the working resolution
  double max_colour_diff = 0.2;      // mean absolute RGB difference of the two pixels
  int64_t max_points = 200000;       // voxel-grid downsampling above this
};

// One view's depth estimate at the working resolution. depth is 0 where there is none.
struct DepthMap {
  Camera camera;       // at the working resolution
  at::Tensor image;    // HxWx3 float, the view's pixels at that resolution
  at::Tensor depth;    // HxW float
  at::Tensor score;    // HxW aggregated ZNCC of the chosen plane
  at::Tensor margin;   // HxW best minus second-best (non-adjacent) score
  at::Tensor support;  // HxW int: source views whose own ZNCC at the chosen plane passes min_score
};

struct DenseStats {
  std::vector<int64_t> depth_pixels;  // valid depths per view
  int64_t fused_before_voxel = 0;
  int64_t points = 0;
  double voxel_size = 0.0;  // 0 when no downsampling was needed
  double seconds = 0.0;
};

struct DenseResult {
  PointCloud points;
  std::vector<DepthMap> depth_maps;
  DenseStats stats;
};

// Depth bounds of `camera` from the sparse points it sees (quantiles, widened by `margin`), else the
// camera's own near/far when valid, else nullopt.
std::optional<std::pair<double, double>> view_depth_range(const Camera& camera, const at::Tensor& xyz,
                                                          const DenseOptions& options);

// Up to max_neighbors source views for `ref`: most shared sparse points first (point_views from the sparse
// stage); without sparse points, the views looking most in the same direction (within 90 degrees).
std::vector<int> select_neighbors(int ref, const std::vector<Camera>& cameras,
                                  const std::vector<std::vector<int>>& point_views, int max_neighbors);

// Plane sweep of one reference view against its sources, all at the same (working) resolution as given.
DepthMap plane_sweep(const Camera& ref_camera, const at::Tensor& ref_image, const std::vector<Camera>& src_cameras,
                     const std::vector<at::Tensor>& src_images, double min_depth, double max_depth,
                     const DenseOptions& options);

// Consistency fusion of all depth maps (each checked against every other view).
PointCloud fuse_depth_maps(const std::vector<DepthMap>& maps, const DenseOptions& options);

// Per-voxel means, over cubic voxels of side `voxel_size` that `xyz` (N x 3) falls in, of each of `values`
// (N x k tensors row-aligned with xyz): one M x k tensor each, M the occupied voxels, in one voxel order.
std::vector<at::Tensor> voxel_means(const at::Tensor& xyz, double voxel_size, const std::vector<at::Tensor>& values);
// Averages points (and colours) per cubic voxel of side `voxel_size`.
PointCloud voxel_downsample(const PointCloud& points, double voxel_size);
// About the smallest voxel whose grid leaves <= max_points of `xyz` (bisection); 0 when the cloud already is
// that small.
double capping_voxel_size(const at::Tensor& xyz, int64_t max_points);
// The voxel-grid downsampling that brings the cloud to <= max_points (or the cloud itself when it already
// is), with capping_voxel_size; *voxel_size gets the size used (0 when none).
PointCloud cap_points(const PointCloud& points, int64_t max_points, double* voxel_size);

// The whole dense stage on the training views. `sparse` bounds the depth range and picks the neighbours
// (may be empty). Fails on invalid input or when no view has a depth range.
absl::StatusOr<DenseResult> dense_reconstruct(const std::vector<Camera>& cameras, const std::vector<at::Tensor>& images,
                                              const SparseResult& sparse, const DenseOptions& options = {});

}  // namespace gaps

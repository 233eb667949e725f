#pragma once
// PatchMatch multi-view stereo on the N training views with their known poses, in the manner of COLMAP
// (Schönberger et al., ECCV 2016), Gipuma and ACMM: a depth and a normal per pixel, random initialisation
// inside the view's depth range, red-black (checkerboard) propagation with random refinement, a bilaterally
// weighted NCC over the homography that the pixel's slanted plane induces in each source view, per-pixel
// source-view selection, then a geometric-consistency pass against the other views' depth maps.
// One semantics, two paths: CUDA kernels for GPU tensors, a CPU loop for CPU tensors (same per-pixel code).
#include <cstdint>
#include <functional>
#include <utility>
#include <vector>

#include <ATen/Tensor.h>
#include "absl/status/statusor.h"
#include "gs_trainer/init/stage_control.h"
#include "gs_trainer/scene/camera.h"

namespace gaps {

struct PatchMatchOptions {
  int max_image_side = 640;  // views are downsampled to this longest side first (fern -r 8 is 504: kept)
  int window_radius = 5;     // NCC window: (2 r + 1)^2 pixels sampled every window_step
  int window_step = 2;
  double sigma_color = 0.2;  // bilateral weight of a window pixel: exp(-|grey - centre grey| / sigma_color)
  int iterations = 6;        // photometric sweeps (each updates the red, then the black pixels)
  int max_source_views = 8;  // candidate source views per reference view (select_neighbors)
  // A hypothesis's cost: the mean over the best this many source views' costs. One, not COLMAP's three: with
  // few views most surfaces are seen well by one or two neighbours only, and a source that cannot judge the
  // point (occluded, outside its image) counts the worst cost, so a mean over more sources stays above max_cost
  // where the best source matches well. Fusion still asks two views' depths to agree, which rejects what one
  // source matched by chance. Trained PSNR (docs/benchmarks.md, "best_views 1"): bonsai 12 views +2.1 dB against
  // 2 (which had gained 1.7 over 3), fern 3 views +1.2, fern 6 unchanged.
  int best_views = 1;
  double min_triangulation_angle_deg = 1.0;  // sources seeing the point under a smaller angle do not count
  // Geometric consistency (COLMAP's geom_consistency): cost + regularizer * min(forward-backward reprojection
  // error in pixels, max_error_px) against the photometric depth maps of the sources.
  bool geometric_consistency = true;
  int geometric_iterations = 2;
  double geometric_regularizer = 0.3;
  double geometric_max_error_px = 3.0;
  double max_cost = 0.6;  // pixels whose final cost (1 - NCC, geometric term included) is higher get depth 0
  uint64_t seed = 0;      // counter-based random numbers: the CPU and CUDA paths draw the same ones
};

// The inputs of one PatchMatch run. images[i] is HxWx3 float in [0, 1] at cameras[i]'s size; all images on
// one device, which decides the path. depth_ranges[i] bounds view i's hypotheses (camera-frame z); (0, 0) means
// the view has none. sources[i] lists view i's candidate source views (indices into cameras, never i itself),
// best first: the first max_source_views of them are used.
struct PatchMatchInput {
  std::vector<Camera> cameras;
  std::vector<at::Tensor> images;
  std::vector<std::pair<double, double>> depth_ranges;
  std::vector<std::vector<int>> sources;
};

// OK, or InvalidArgument naming the first option out of its range.
absl::Status validate_patchmatch_options(const PatchMatchOptions& options);

// One view's result at the working resolution (CPU tensors).
struct ViewDepthNormal {
  Camera camera;      // at the working resolution
  at::Tensor image;   // HxWx3 float in [0, 1]
  at::Tensor depth;   // HxW float, camera-frame z; 0 where no estimate survived
  at::Tensor normal;  // HxWx3 float, unit, camera frame, facing the camera (COLMAP's convention); 0 where depth is
  at::Tensor cost;    // HxW float, final aggregated cost of the kept hypothesis
};

// Depth and normal maps for every view (views without sources or range come back with depth all 0).
// Errors name the problem: mismatched sizes, an image not HxWx3, an empty or inverted depth range, a source
// index out of range, images on different devices, CUDA asked for in a build without the kernels.
// `control.should_stop` is asked before every sweep (true ends it with CANCELLED); `control.on_progress` hears
// ("patchmatch", sweeps done, sweeps in all) after each.
absl::StatusOr<std::vector<ViewDepthNormal>> patchmatch_stereo(const PatchMatchInput& input,
                                                               const PatchMatchOptions& options = {},
                                                               const StageControl& control = {});

}  // namespace gaps

#pragma once
// Initial point cloud for training from the N training views only (the sparse-view protocol: nothing from
// the test views). Methods, in the order of the honest fallback chain:
//   "mvs"    sparse triangulation, then PatchMatch stereo + fusion (dense_mvs.h);
//   "sweep"  sparse triangulation, then the older fronto-parallel plane sweep + fusion (plane_sweep.h);
//   "sparse" SIFT matching + triangulation with the known poses (sparse.h);
//   "random" uniform points in the cameras' frusta (gaussians.h).
// A method that cannot produce enough points falls back to the next one and says why in the report.
// "auto" is "mvs" asking its depth maps to cover kAutoMinDepthCoverage of the pixels (else the sparse points).
#include <cstdint>
#include <filesystem>
#include <functional>
#include <optional>
#include <string>
#include <vector>

#include <ATen/Tensor.h>
#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "gs_trainer/init/dense_mvs.h"
#include "gs_trainer/init/fusion.h"
#include "gs_trainer/init/patchmatch.h"
#include "gs_trainer/init/plane_sweep.h"
#include "gs_trainer/init/sparse.h"
#include "gs_trainer/scene/camera.h"
#include "gs_trainer/scene/scene.h"

namespace gaps {

struct InitOptions {
  // Results are cached here as <key>.ply + <key>.json (see init_cache_key); empty: no cache.
  std::filesystem::path cache_dir;
  int64_t random_points = 20000;
  uint64_t seed = 0;
  SparseOptions sparse;
  DenseOptions dense;              // "sweep"; its depth_margin and min_points_for_range also bound "mvs"'s depth ranges
  PatchMatchOptions patchmatch;    // "mvs"
  FusionOptions fusion;            // "mvs"
  int64_t min_sparse_points = 50;  // fewer triangulated points: "sparse" has failed
  int64_t min_dense_points = 1000;  // fewer fused points: "mvs" or "sweep" has failed
  // "mvs" has failed when its depth maps give a depth to less than this fraction of the views' pixels (at
  // the working resolution): a cloud of the few well-matched regions leaves the rest of the scene without
  // points. 0 for an explicit --init mvs; "auto" asks kAutoMinDepthCoverage.
  double min_depth_coverage = 0.0;
  // Non-empty: when "mvs" makes the points, its depth and normal maps and fused cloud are also written here
  // as a COLMAP dense workspace (colmap_dense.h). Only a computation has the maps, so the cache is then
  // written but not read.
  std::filesystem::path dense_workspace;
  // Asked between the stages and between PatchMatch's sweeps: true ends the initialisation with CANCELLED,
  // caching nothing (a cancelled job, a stopping service: on a CPU PatchMatch alone takes minutes).
  std::function<bool()> should_stop;
  // Told how far the long stages have come: ("sparse", 0 or 1, 1), ("patchmatch", sweeps done, in all),
  // ("fusion", 0 or 1, 1), ("sweep", 0 or 1, 1). Not called for a cached result or random points.
  std::function<void(const std::string& stage, int done, int total)> on_progress;
};

struct InitResult {
  PointCloud points;                  // CPU tensors
  std::string method;                 // the method that produced the points
  std::vector<std::string> warnings;  // one per fallback, saying why
  std::vector<std::string> notes;     // per-stage statistics, one line each
  std::optional<SparseStats> sparse;
  std::optional<DenseStats> dense;  // "sweep"
  std::optional<MvsStats> mvs;
  std::filesystem::path cache_file;  // the PLY read or written (empty without a cache)
  bool from_cache = false;
};

// The methods run_initialization knows: auto, mvs, sweep, sparse, random.
bool is_init_method(const std::string& name);

// Training views whose viewing directions differ by more than this surround the scene (a 360° capture).
inline constexpr double kSurroundingViewsDegrees = 90.0;

// Largest angle in degrees between two cameras' viewing directions (0 for fewer than two cameras).
double viewing_direction_spread_degrees(const std::vector<Camera>& cameras);

// Whether the views surround the scene (their viewing directions spread over more than
// kSurroundingViewsDegrees): what decides the paper's pseudo-views per phase (GapsConfig).
bool views_surround_scene(const std::vector<Camera>& cameras);

// "auto" is PatchMatch ("mvs") with this depth coverage asked of it (InitOptions::min_depth_coverage), so that a
// capture too sparse for PatchMatch to give a quarter of the pixels a depth takes the sparse points instead.
// PatchMatch trains best or as well as the alternatives on every capture measured (docs/benchmarks.md, "best_views
// 1"): fern 3 views 20.9 / 22.5 dB (vanilla / full) against the plane sweep's 20.8 / 22.3, fern 6 and 9
// 0.1–0.2 dB ahead of the sweep, bonsai 12 views 19.4 / 20.0 against the sparse points' 17.1 / 18.1, bonsai 24
// (best_views 2) 24.2 / 24.8 against 22.7 / 23.6.
inline constexpr double kAutoMinDepthCoverage = 0.25;

// The full result. images[i] is HxWx3 float in [0, 1] at cameras[i]'s size, on any device. Errors only for
// an unknown method or invalid input; everything else falls back (see above).
absl::StatusOr<InitResult> run_initialization(const std::string& method, const std::vector<Camera>& train_cameras,
                                              const std::vector<at::Tensor>& train_images, const InitOptions& opts);

// The points only; *report (if given) gets the statistics and the warning lines, newline-terminated,
// *method_used (if given) the method that made the points ("auto" resolved, fallbacks taken) and *from_cache
// (if given) whether they were read from the cache instead of computed.
absl::StatusOr<PointCloud> initialize_points(const std::string& method, const std::vector<Camera>& train_cameras,
                                             const std::vector<at::Tensor>& train_images, const InitOptions& opts,
                                             std::string* report, std::string* method_used = nullptr,
                                             bool* from_cache = nullptr);

// Cache file stem: <scene>_<N>v_<W>x<H>_<method>_<16 hex digits> where the hash covers the method, every
// camera (name, size, intrinsics, pose, bounds), a fingerprint of every image and the options (the PatchMatch
// and fusion ones for "mvs" and "auto" only).
std::string init_cache_key(const std::string& method, const std::vector<Camera>& cameras,
                           const std::vector<at::Tensor>& images, const InitOptions& opts);

// cameras.txt / images.txt / points3D.txt in `dir` (one PINHOLE camera per view, ids from 1; points without
// tracks), so COLMAP users can inspect our points or replace them with their own reconstruction.
absl::Status write_init_as_colmap(const std::filesystem::path& dir, const std::vector<Camera>& cameras,
                                  const PointCloud& points);

// Fraction of the camera's cell x cell pixel blocks that at least one point (in front of it) projects into.
double view_coverage(const Camera& camera, const at::Tensor& xyz, int cell = 16);

}  // namespace gaps

#include "gs_trainer/init/initializer.h"

#include <algorithm>
#include <cmath>
#include <system_error>

#include <ATen/ATen.h>
#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "absl/strings/str_join.h"
#include "common/io_util.h"
#include "common/ply.h"
#include "common/status_macros.h"
#include "gs_trainer/init/colmap_dense.h"
#include "gs_trainer/init/init_cache.h"
#include "gs_trainer/scene/bounds.h"
#include "gs_trainer/scene/colmap.h"

namespace gaps {
namespace {

namespace fs = std::filesystem;

// Bumped whenever an algorithm or default changes what a method produces, so stale caches are not reused.
constexpr char kCacheVersion[] = "init-v3";

// Every method, in the order messages list them.
constexpr const char* kInitMethods[] = {"auto", "mvs", "sweep", "sparse", "random"};

std::string scene_name(const std::vector<Camera>& cameras) {
  // image_path is <scene>/<images folder>/<file>; synthetic cameras may have none.
  std::string name = cameras.empty() ? "" : cameras[0].image_path.parent_path().parent_path().filename().string();
  for (char& c : name)
    if (!std::isalnum(static_cast<unsigned char>(c)) && c != '-' && c != '_') c = '_';
  return name.empty() ? "scene" : name;
}

std::string describe_options(const InitOptions& o) {
  const SparseOptions& s = o.sparse;
  const DenseOptions& d = o.dense;
  return absl::StrFormat(
      "random %d seed %d minpts %d %d | sparse %d %.6g %.6g %.6g %.6g %.6g %d %d | dense %d %d %d %d %d %.6g %d %.6g "
      "%.6g %.6g %d %.6g %.6g %.6g %d",
      o.random_points, o.seed, o.min_sparse_points, o.min_dense_points, s.max_features, s.contrast_threshold, s.ratio,
      s.max_epipolar_px, s.max_reprojection_px, s.min_angle_deg, s.refine_iterations, s.max_image_side,
      d.max_image_side, d.num_planes, d.window, d.max_neighbors, d.planes_per_chunk, d.depth_margin,
      d.min_points_for_range, d.min_score, d.min_margin, d.min_texture_std, d.min_consistent_views,
      d.max_relative_depth_diff, d.max_reprojection_px, d.max_colour_diff, d.max_points);
}

std::string describe_mvs_options(const PatchMatchOptions& p, const FusionOptions& f, double min_depth_coverage) {
  return absl::StrFormat(
      "patchmatch %d %d %d %.6g %d %d %d %.6g %d %d %.6g %.6g %.6g %d | fusion %.6g %.6g %.6g %d %d %d"
      " | coverage %.6g",
      p.max_image_side, p.window_radius, p.window_step, p.sigma_color, p.iterations, p.max_source_views, p.best_views,
      p.min_triangulation_angle_deg, p.geometric_consistency, p.geometric_iterations, p.geometric_regularizer,
      p.geometric_max_error_px, p.max_cost, p.seed, f.max_depth_error, f.max_reprojection_px, f.max_normal_error_deg,
      f.min_views, f.max_points, f.add_sparse_points, min_depth_coverage);
}

std::string describe_camera(const Camera& c, const at::Tensor& image) {
  std::string text = absl::StrFormat("%s %dx%d %.10g %.10g %.10g %.10g %.10g %.10g", c.name, c.width, c.height, c.fx,
                                     c.fy, c.cx, c.cy, c.near, c.far);
  for (int i = 0; i < 9; ++i) absl::StrAppend(&text, absl::StrFormat(" %.10g", c.R(i / 3, i % 3)));
  for (int i = 0; i < 3; ++i) absl::StrAppend(&text, absl::StrFormat(" %.10g", c.t(i)));
  // The pixels matter too (same names, other images): their sum is a cheap fingerprint.
  absl::StrAppend(&text, absl::StrFormat(" sum %.9g", image.to(at::kDouble).sum().item<double>()));
  return text;
}

absl::Status check_inputs(const std::string& method, const std::vector<Camera>& cameras,
                          const std::vector<at::Tensor>& images) {
  if (!is_init_method(method))
    return absl::InvalidArgumentError(
        absl::StrCat("unknown initialisation '", method, "' (", absl::StrJoin(kInitMethods, ", "), ")"));
  if (cameras.empty()) return absl::InvalidArgumentError("initialisation needs at least one training view");
  return check_view_images(cameras, images);
}

PointCloud random_cloud(const std::vector<Camera>& cameras, const InitOptions& opts) {
  double far = 0;
  for (const Camera& c : cameras) far = std::max(far, c.far);
  if (far <= 0) far = default_far_bound(cameras);
  return random_points_in_views(cameras, opts.random_points, far, opts.seed);
}

bool all_centres_coincide(const std::vector<Camera>& cameras) {
  const double scale = 1e-9 * (1.0 + cameras[0].center().norm());
  for (const Camera& c : cameras)
    if ((c.center() - cameras[0].center()).norm() > scale) return false;
  return true;
}

std::string sparse_note(const SparseStats& s) {
  return absl::StrFormat(
      "sparse: %d keypoints, %d ratio-test matches, %d epipolar-consistent, %d tracks -> %d points (rejected: %d "
      "cheirality, %d reprojection, %d angle), median reprojection %.3f px, %.1f s",
      s.keypoints, s.ratio_matches, s.epipolar_matches, s.tracks, s.points, s.rejected_cheirality,
      s.rejected_reprojection, s.rejected_angle, s.median_reprojection_px, s.seconds);
}

std::string dense_note(const DenseStats& d) {
  return absl::StrFormat(
      "sweep: depth pixels per view [%s], %d fused points -> %d after voxel grid (voxel %.4g), %.1f s",
      absl::StrJoin(d.depth_pixels, ", "), d.fused_before_voxel, d.points, d.voxel_size, d.seconds);
}

std::string mvs_note(const MvsStats& m, const FusionOptions& o) {
  const FusionStats& f = m.fusion;
  return absl::StrFormat(
      "mvs: PatchMatch on %d views, %.1f s; depth pixels per view [%s]; fusion: %d clusters -> %d points in >= %d "
      "views -> %d after voxel grid (voxel %.4g, cap %s), %.1f s",
      m.views_with_sources, m.patchmatch_seconds, absl::StrJoin(f.depth_pixels, ", "), f.clusters, f.fused_points,
      o.min_views, f.points, f.voxel_size, o.max_points > 0 ? absl::StrCat(o.max_points) : "none", f.seconds);
}

// The fused cloud with the sparse stage's points added (FusionOptions::add_sparse_points), capped at
// max_points as one cloud; *note says what was added.
PointCloud add_sparse_points(const PointCloud& fused, const PointCloud& sparse, int64_t max_points, std::string* note) {
  if (!sparse.xyz.defined() || sparse.xyz.size(0) == 0) {
    *note = "mvs: no sparse points to add";
    return fused;
  }
  const auto cpu = [](const at::Tensor& t) { return t.to(at::kCPU, at::kFloat); };
  const PointCloud merged{at::cat({cpu(fused.xyz), cpu(sparse.xyz)}), at::cat({cpu(fused.rgb), cpu(sparse.rgb)})};
  double voxel_size = 0.0;
  PointCloud capped = max_points > 0 ? cap_points(merged, max_points, &voxel_size) : merged;
  *note = absl::StrFormat("mvs: %d fused + %d sparse points -> %d (voxel %.4g)", fused.xyz.size(0), sparse.xyz.size(0),
                          capped.xyz.size(0), voxel_size);
  return capped;
}

// Why triangulation gave too few points, from its statistics.
std::string sparse_failure(const SparseStats& s, int views, const InitOptions& opts) {
  const int pairs = views * (views - 1) / 2;
  if (s.degenerate_pairs == pairs) return "degenerate baseline: every pair of training cameras shares one centre";
  if (s.epipolar_matches < opts.min_sparse_points)
    return absl::StrCat("too few matches (", s.keypoints, " keypoints, ", s.ratio_matches, " pass the ratio test, ",
                        s.epipolar_matches, " agree with the poses' epipolar geometry)");
  if (s.rejected_angle * 2 >= s.tracks)
    return absl::StrCat("degenerate baseline: ", s.rejected_angle, " of ", s.tracks,
                        " tracks have triangulation angles under ", opts.sparse.min_angle_deg, " degrees");
  return absl::StrCat("too few triangulated points (", s.points, " of ", s.tracks, " tracks; need ",
                      opts.min_sparse_points, ")");
}

// Why a dense method's cloud is too small to train from; "" when it is large enough.
std::string too_few_fused(int64_t points, const InitOptions& opts) {
  if (points >= opts.min_dense_points) return "";
  return absl::StrCat("too few fused points (", points, " < ", opts.min_dense_points, ")");
}

// Why PatchMatch's maps give too few pixels a depth (InitOptions::min_depth_coverage); "" when they do not.
std::string too_little_depth(const std::vector<ViewDepthNormal>& maps, const FusionStats& fusion,
                             const InitOptions& opts) {
  if (opts.min_depth_coverage <= 0) return "";
  int64_t pixels = 0, with_depth = 0;
  for (const ViewDepthNormal& m : maps) pixels += int64_t{m.camera.width} * m.camera.height;
  for (int64_t n : fusion.depth_pixels) with_depth += n;
  const double coverage = pixels > 0 ? static_cast<double>(with_depth) / pixels : 0.0;
  if (coverage >= opts.min_depth_coverage) return "";
  return absl::StrFormat("depth for %.0f%% of the pixels (< %.0f%%)", 100 * coverage, 100 * opts.min_depth_coverage);
}

// "mvs" or "sweep" after the sparse stage: the points and statistics go into *r, the return value says why
// the method failed (empty when it did not). Errors only for a dense workspace that cannot be written.
absl::StatusOr<std::string> dense_stage(const std::string& method, const std::vector<Camera>& cameras,
                                        const std::vector<at::Tensor>& images, const SparseResult& sparse,
                                        const InitOptions& opts, InitResult* r) {
  const StageControl control{opts.should_stop, opts.on_progress};
  if (method == "sweep") {
    control.progress("sweep", 0, 1);
    auto dense = dense_reconstruct(cameras, images, sparse, opts.dense);
    control.progress("sweep", 1, 1);
    if (!dense.ok()) return std::string(dense.status().message());
    r->dense = dense->stats;
    r->notes.push_back(dense_note(dense->stats));
    const std::string why = too_few_fused(dense->stats.points, opts);
    if (why.empty()) {
      r->points = std::move(dense->points);
      r->method = method;
    }
    return why;
  }
  auto mvs = patchmatch_reconstruct(cameras, images, sparse, opts.patchmatch, opts.fusion, opts.dense, control);
  if (absl::IsCancelled(mvs.status())) return mvs.status();  // stopped, not failed: no fallback
  if (!mvs.ok()) return std::string(mvs.status().message());
  r->mvs = mvs->stats;
  r->notes.push_back(mvs_note(mvs->stats, opts.fusion));
  std::string why = too_few_fused(mvs->stats.fusion.points, opts);
  if (why.empty()) why = too_little_depth(mvs->maps, mvs->stats.fusion, opts);
  if (!why.empty()) return why;
  if (!opts.dense_workspace.empty())
    GAPS_RETURN_IF_ERROR(write_colmap_dense_workspace(opts.dense_workspace, mvs->maps, mvs->fused, sparse.points));
  r->points = std::move(mvs->fused.points);
  if (opts.fusion.add_sparse_points) {
    std::string note;
    r->points = add_sparse_points(r->points, sparse.points, opts.fusion.max_points, &note);
    r->notes.push_back(note);
  }
  r->method = method;
  return why;
}

absl::Status stop_requested(const InitOptions& opts, absl::string_view where) {
  if (opts.should_stop && opts.should_stop())
    return absl::CancelledError(absl::StrCat("initialisation stopped ", where));
  return absl::OkStatus();
}

// The fallback chain, without the cache.
absl::StatusOr<InitResult> compute(const std::string& method, const std::vector<Camera>& cameras,
                                   const std::vector<at::Tensor>& images, const InitOptions& opts) {
  InitResult r;
  const auto fall_back_to_random = [&](const std::string& why) {
    if (!why.empty()) r.warnings.push_back(absl::StrCat(why, "; falling back to random points"));
    r.points = random_cloud(cameras, opts);
    r.method = "random";
    return r;
  };
  if (method == "random") return fall_back_to_random("");
  if (cameras.size() < 2)
    return fall_back_to_random(absl::StrCat(method, " needs at least two views, got a single training view"));
  if (all_centres_coincide(cameras))
    return fall_back_to_random(
        absl::StrCat(method, ": degenerate baseline, all ", cameras.size(), " training cameras share one centre"));

  GAPS_RETURN_IF_ERROR(stop_requested(opts, "before the sparse points"));
  if (opts.on_progress) opts.on_progress("sparse", 0, 1);
  GAPS_ASSIGN_OR_RETURN(SparseResult sparse, sparse_reconstruct(cameras, images, opts.sparse));
  if (opts.on_progress) opts.on_progress("sparse", 1, 1);
  GAPS_RETURN_IF_ERROR(stop_requested(opts, "after the sparse points"));
  r.sparse = sparse.stats;
  r.notes.push_back(sparse_note(sparse.stats));
  const bool sparse_ok = sparse.stats.points >= opts.min_sparse_points;
  const std::string sparse_why = sparse_ok ? "" : sparse_failure(sparse.stats, static_cast<int>(cameras.size()), opts);

  if (method == "mvs" || method == "sweep") {
    // Runs even when triangulation failed: the cameras' near/far may still bound the depths.
    GAPS_ASSIGN_OR_RETURN(const std::string why, dense_stage(method, cameras, images, sparse, opts, &r));
    if (why.empty()) return r;
    const std::string failed = absl::StrCat(method, " failed: ", why);
    if (!sparse_ok) return fall_back_to_random(absl::StrCat(failed, "; sparse: ", sparse_why));
    r.warnings.push_back(absl::StrCat(failed, "; falling back to the sparse points"));
  }
  if (!sparse_ok) return fall_back_to_random(absl::StrCat("sparse failed: ", sparse_why));
  r.points = std::move(sparse.points);
  r.method = "sparse";
  return r;
}

}  // namespace

std::string init_cache_key(const std::string& method, const std::vector<Camera>& cameras,
                           const std::vector<at::Tensor>& images, const InitOptions& opts) {
  std::string text = absl::StrCat(kCacheVersion, "|", method, "|", describe_options(opts));
  // Only where they matter: the fusion cap follows the run's Gaussian budget, which should not invalidate
  // the sparse points.
  if (method == "mvs" || method == "auto")
    absl::StrAppend(&text, "|", describe_mvs_options(opts.patchmatch, opts.fusion, opts.min_depth_coverage));
  for (size_t i = 0; i < cameras.size(); ++i)
    absl::StrAppend(&text, "|", describe_camera(cameras[i], i < images.size() ? images[i] : at::zeros({1})));
  const int w = cameras.empty() ? 0 : cameras[0].width, h = cameras.empty() ? 0 : cameras[0].height;
  return absl::StrFormat("%s_%dv_%dx%d_%s_%016x", scene_name(cameras), cameras.size(), w, h, method, fnv1a(text));
}

namespace {

// A cache file of `key` under another scene name: the name is only the folder the images came from (a
// service job's is "scene"), while the rest of the key covers cameras, pixels and settings. This is how
// gaps train and a trainer sharing one cache folder reuse each other's clouds.
std::optional<fs::path> same_key_other_name(const fs::path& dir, const std::string& key, const std::string& name) {
  const std::string rest = key.substr(name.size()) + ".ply";
  std::error_code ec;
  for (fs::directory_iterator it(dir, ec), end; !ec && it != end; it.increment(ec)) {
    const std::string file = it->path().filename().string();
    if (file.size() > rest.size() && file.compare(file.size() - rest.size(), rest.size(), rest) == 0) return it->path();
  }
  return std::nullopt;
}

}  // namespace

bool is_init_method(const std::string& name) {
  return std::find(std::begin(kInitMethods), std::end(kInitMethods), name) != std::end(kInitMethods);
}

double viewing_direction_spread_degrees(const std::vector<Camera>& cameras) {
  double min_cosine = 1.0;
  for (size_t i = 0; i < cameras.size(); ++i)
    for (size_t j = i + 1; j < cameras.size(); ++j)
      min_cosine = std::min(min_cosine, cameras[i].forward().normalized().dot(cameras[j].forward().normalized()));
  return std::acos(std::clamp(min_cosine, -1.0, 1.0)) * 180.0 / M_PI;
}

bool views_surround_scene(const std::vector<Camera>& cameras) {
  return viewing_direction_spread_degrees(cameras) > kSurroundingViewsDegrees;
}

namespace {

absl::StatusOr<InitResult> cached_or_computed(const std::string& method, const std::vector<Camera>& train_cameras,
                                              const std::vector<at::Tensor>& train_images, const InitOptions& opts) {
  fs::path cache;
  // Random points cost nothing to draw again; caching them would only hide changes.
  if (!opts.cache_dir.empty() && method != "random") {
    const std::string key = init_cache_key(method, train_cameras, train_images, opts);
    cache = opts.cache_dir / (key + ".ply");
    const bool needs_maps = method == "mvs" && !opts.dense_workspace.empty();
    if (std::optional<InitResult> cached = needs_maps ? std::nullopt : read_init_cache(cache))
      return std::move(*cached);
    if (const auto other =
            needs_maps ? std::nullopt : same_key_other_name(opts.cache_dir, key, scene_name(train_cameras)))
      if (std::optional<InitResult> cached = read_init_cache(*other)) return std::move(*cached);
  }
  GAPS_ASSIGN_OR_RETURN(InitResult r, compute(method, train_cameras, train_images, opts));
  r.points.xyz = r.points.xyz.to(at::kCPU, at::kFloat).contiguous();
  r.points.rgb = r.points.rgb.to(at::kCPU, at::kFloat).contiguous();
  if (!cache.empty()) {
    auto stored = write_init_cache(cache, r);
    if (stored.ok()) {
      r.points = std::move(*stored);
      r.cache_file = cache;
    } else {
      r.warnings.push_back(absl::StrCat("cache not written: ", stored.status().message()));
    }
  }
  return r;
}

}  // namespace

absl::StatusOr<InitResult> run_initialization(const std::string& method, const std::vector<Camera>& train_cameras,
                                              const std::vector<at::Tensor>& train_images, const InitOptions& opts) {
  GAPS_RETURN_IF_ERROR(check_inputs(method, train_cameras, train_images));
  if (method != "auto") return cached_or_computed(method, train_cameras, train_images, opts);
  InitOptions auto_opts = opts;
  auto_opts.min_depth_coverage = std::max(opts.min_depth_coverage, kAutoMinDepthCoverage);
  GAPS_ASSIGN_OR_RETURN(InitResult r, cached_or_computed("mvs", train_cameras, train_images, auto_opts));
  r.notes.insert(r.notes.begin(), absl::StrFormat("auto: mvs, the sparse points if its depth maps cover under %.0f%% "
                                                  "of the pixels",
                                                  100 * kAutoMinDepthCoverage));
  return r;
}

absl::StatusOr<PointCloud> initialize_points(const std::string& method, const std::vector<Camera>& train_cameras,
                                             const std::vector<at::Tensor>& train_images, const InitOptions& opts,
                                             std::string* report, std::string* method_used, bool* from_cache) {
  GAPS_ASSIGN_OR_RETURN(InitResult r, run_initialization(method, train_cameras, train_images, opts));
  if (method_used) *method_used = r.method;
  if (from_cache) *from_cache = r.from_cache;
  if (report) {
    std::string& out = *report;
    if (r.from_cache) absl::StrAppend(&out, "init: reusing ", r.cache_file.string(), " (computed earlier:)\n");
    for (const std::string& n : r.notes) absl::StrAppend(&out, "init: ", n, "\n");
    for (const std::string& w : r.warnings) absl::StrAppend(&out, "warning: init: ", w, "\n");
    absl::StrAppend(
        &out, "init: ", r.method, ", ", r.points.xyz.size(0), " points from ", train_cameras.size(), " training views",
        r.from_cache || r.cache_file.empty() ? "" : absl::StrCat(", cached in ", r.cache_file.string()), "\n");
  }
  return std::move(r.points);
}

absl::Status write_init_as_colmap(const std::filesystem::path& dir, const std::vector<Camera>& cameras,
                                  const PointCloud& points) {
  return write_colmap_text(dir, colmap_from_cameras(cameras, points));
}

double view_coverage(const Camera& camera, const at::Tensor& xyz, int cell) {
  const int cols = (camera.width + cell - 1) / cell, rows = (camera.height + cell - 1) / cell;
  if (cols <= 0 || rows <= 0) return 0.0;
  std::vector<char> hit(static_cast<size_t>(cols) * rows, 0);
  const at::Tensor pts = xyz.to(at::kCPU, at::kDouble).contiguous();
  const auto a = pts.accessor<double, 2>();
  for (int64_t i = 0; i < pts.size(0); ++i) {
    const auto p = project_point(camera, Eigen::Vector3d(a[i][0], a[i][1], a[i][2]));
    if (!p || p->x() < 0 || p->y() < 0 || p->x() >= camera.width || p->y() >= camera.height) continue;
    hit[static_cast<size_t>(p->y() / cell) * cols + static_cast<size_t>(p->x() / cell)] = 1;
  }
  return static_cast<double>(std::count(hit.begin(), hit.end(), 1)) / hit.size();
}

}  // namespace gaps

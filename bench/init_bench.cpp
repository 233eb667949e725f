// Point-cloud initialisation from the sparse training views on the benchmark scenes: points from the sparse
// stage and after fusion, the sparse median reprojection error, how much of the held-out test views the
// points cover (fraction of 16x16 pixel cells hit), and the time. One JSON line per case.
//   init_bench --method mvs --fern_views 3,6,9 --bonsai_views 12,24 --resolution 8 --json out.jsonl
// mvs is PatchMatch + fusion, sweep the plane sweep; fusion is capped at --fusion_max_points (0: no cap; -1:
// the Gaussian budget of a default training run, which caps it so).
#include <chrono>
#include <filesystem>
#include <fstream>
#include <iostream>
#include <string>
#include <vector>

#include <ATen/ATen.h>
#include <ATen/Parallel.h>
#include <nlohmann/json.hpp>
#include "absl/flags/flag.h"
#include "absl/flags/parse.h"
#include "absl/strings/numbers.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_split.h"
#include "common/ply.h"
#include "gs_trainer/init/initializer.h"
#include "gs_trainer/train/budget.h"
#include "gs_trainer/train/train_config.h"
#include "gs_trainer/train/trainer.h"

ABSL_FLAG(std::string, method, "mvs", "mvs, sweep, sparse or random");
ABSL_FLAG(std::string, fern_views, "3,6,9", "training view counts on LLFF fern (empty: skip)");
ABSL_FLAG(std::string, bonsai_views, "12,24", "training view counts on Mip-NeRF 360 bonsai (empty: skip)");
ABSL_FLAG(int, resolution, 8, "downscale factor");
ABSL_FLAG(std::string, device, "cpu", "cpu or cuda: where the images (and so the dense stage) live");
ABSL_FLAG(std::string, json, "", "append the result lines to this file");
// Overrides of the initialisation options (defaults: InitOptions{}).
ABSL_FLAG(bool, guided_matching, gaps::SparseOptions{}.guided_matching, "epipolar-guided matching");
ABSL_FLAG(double, contrast_threshold, gaps::SparseOptions{}.contrast_threshold, "SIFT contrast threshold");
ABSL_FLAG(int, max_features, gaps::SparseOptions{}.max_features, "SIFT keypoints per image");
ABSL_FLAG(int, sparse_max_image_side, gaps::SparseOptions{}.max_image_side,
          "SIFT and triangulation on the views downsampled to this longest side (0: as read)");
ABSL_FLAG(int, max_image_side, gaps::DenseOptions{}.max_image_side, "plane-sweep working resolution");
ABSL_FLAG(int, patchmatch_max_image_side, gaps::PatchMatchOptions{}.max_image_side, "PatchMatch working resolution");
ABSL_FLAG(int, patchmatch_iterations, gaps::PatchMatchOptions{}.iterations, "PatchMatch photometric sweeps");
ABSL_FLAG(bool, geometric_consistency, gaps::PatchMatchOptions{}.geometric_consistency,
          "PatchMatch geometric-consistency pass");
ABSL_FLAG(std::string, ply_dir, "",
          "also write each case's cloud to DIR/SCENE_Vv_METHOD.ply (for gaps train --init-ply; empty: not written)");
ABSL_FLAG(int, patchmatch_best_views, gaps::PatchMatchOptions{}.best_views,
          "PatchMatch: sources whose costs a hypothesis's cost averages");
ABSL_FLAG(double, patchmatch_max_cost, gaps::PatchMatchOptions{}.max_cost,
          "PatchMatch: pixels whose final cost is higher get no depth");
ABSL_FLAG(int, fusion_min_views, gaps::FusionOptions{}.min_views, "views a fused point must span");
ABSL_FLAG(bool, fusion_add_sparse, gaps::FusionOptions{}.add_sparse_points,
          "add the sparse stage's points to the fused cloud");
ABSL_FLAG(int64_t, fusion_max_points, gaps::FusionOptions{}.max_points,
          "cap on the fused points (0: none; -1: the automatic Gaussian budget of a default run, as `gaps train "
          "--init mvs` caps them, so that a cloud written with --ply_dir trains as that run's would)");
ABSL_FLAG(int, num_planes, gaps::DenseOptions{}.num_planes, "plane-sweep depth hypotheses");
ABSL_FLAG(int, max_neighbors, gaps::DenseOptions{}.max_neighbors, "plane-sweep source views");
ABSL_FLAG(int, planes_per_chunk, gaps::DenseOptions{}.planes_per_chunk, "planes warped at once");

namespace {

gaps::InitOptions init_options() {
  gaps::InitOptions o;
  o.sparse.guided_matching = absl::GetFlag(FLAGS_guided_matching);
  o.sparse.contrast_threshold = absl::GetFlag(FLAGS_contrast_threshold);
  o.sparse.max_features = absl::GetFlag(FLAGS_max_features);
  o.sparse.max_image_side = absl::GetFlag(FLAGS_sparse_max_image_side);
  o.dense.max_image_side = absl::GetFlag(FLAGS_max_image_side);
  o.dense.num_planes = absl::GetFlag(FLAGS_num_planes);
  o.dense.max_neighbors = absl::GetFlag(FLAGS_max_neighbors);
  o.dense.planes_per_chunk = absl::GetFlag(FLAGS_planes_per_chunk);
  o.patchmatch.max_image_side = absl::GetFlag(FLAGS_patchmatch_max_image_side);
  o.patchmatch.iterations = absl::GetFlag(FLAGS_patchmatch_iterations);
  o.patchmatch.geometric_consistency = absl::GetFlag(FLAGS_geometric_consistency);
  o.patchmatch.best_views = absl::GetFlag(FLAGS_patchmatch_best_views);
  o.patchmatch.max_cost = absl::GetFlag(FLAGS_patchmatch_max_cost);
  o.fusion.min_views = absl::GetFlag(FLAGS_fusion_min_views);
  o.fusion.add_sparse_points = absl::GetFlag(FLAGS_fusion_add_sparse);
  o.fusion.max_points = absl::GetFlag(FLAGS_fusion_max_points);
  return o;
}

std::vector<int> parse_counts(const std::string& text) {
  std::vector<int> counts;
  for (absl::string_view part : absl::StrSplit(text, ',', absl::SkipEmpty())) {
    int n = 0;
    if (absl::SimpleAtoi(part, &n)) counts.push_back(n);
  }
  return counts;
}

// The Gaussian budget a `gaps train` run would have on these views at the default density
// (kDefaultGaussiansPerVariation; run/initial_model.cpp caps the fused points at it). `--init auto` on forward-facing
// views uses kAutoLargerViewsGaussiansPerVariation instead (with_auto_budget); this bench runs one method at a time.
int64_t default_run_budget(const std::vector<gaps::Camera>& cams, const std::vector<at::Tensor>& images) {
  std::vector<gaps::TrainingView> views;
  for (size_t i = 0; i < cams.size(); ++i) views.push_back({cams[i], images[i]});
  const gaps::TrainConfig defaults;
  return gaps::gaussian_budget(defaults.max_gaussians, defaults.gaussians_per_variation, views);
}

// One case; the JSON line, or an "error" field saying what failed.
nlohmann::json run_case(const std::string& scene_name, const std::filesystem::path& root, int views) {
  nlohmann::json j = {{"scene", scene_name}, {"views", views}, {"resolution", absl::GetFlag(FLAGS_resolution)}};
  const auto fail = [&j](const absl::Status& status) {
    j["error"] = std::string(status.message());
    return j;
  };
  gaps::SceneLoadOptions load;
  load.resolution = absl::GetFlag(FLAGS_resolution);
  auto scene = gaps::load_scene(root, load);
  if (!scene.ok()) return fail(scene.status());
  auto split = gaps::benchmark_split(static_cast<int>(scene->cameras.size()), views);
  if (!split.ok()) return fail(split.status());
  std::vector<gaps::Camera> cams;
  std::vector<at::Tensor> images;
  const at::Device device(absl::GetFlag(FLAGS_device));
  for (int i : split->train) {
    auto image = gaps::load_camera_image(scene->cameras[i]);
    if (!image.ok()) return fail(image.status());
    cams.push_back(scene->cameras[i]);
    images.push_back(image->to(device));
  }
  gaps::InitOptions options = init_options();
  if (options.fusion.max_points < 0) options.fusion.max_points = default_run_budget(cams, images);
  const auto start = std::chrono::steady_clock::now();
  auto result = gaps::run_initialization(absl::GetFlag(FLAGS_method), cams, images, options);
  const double seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
  if (!result.ok()) return fail(result.status());

  double coverage_sum = 0, coverage_min = 1;
  for (int i : split->test) {
    const double c = gaps::view_coverage(scene->cameras[i], result->points.xyz);
    coverage_sum += c;
    coverage_min = std::min(coverage_min, c);
  }
  j["size"] = std::to_string(cams[0].width) + "x" + std::to_string(cams[0].height);
  j["method"] = result->method;
  j["requested"] = absl::GetFlag(FLAGS_method);
  j["points"] = result->points.xyz.size(0);
  if (result->sparse) {
    j["keypoints"] = result->sparse->keypoints;
    j["matches"] = result->sparse->epipolar_matches;
    j["tracks"] = result->sparse->tracks;
    j["sparse_points"] = result->sparse->points;
    j["median_reprojection_px"] = result->sparse->median_reprojection_px;
    j["sparse_seconds"] = result->sparse->seconds;
    j["sparse_max_image_side"] = options.sparse.max_image_side;
  }
  if (result->dense) {
    j["fused_points"] = result->dense->fused_before_voxel;
    j["fused_points_capped"] = result->dense->points;
    j["dense_seconds"] = result->dense->seconds;
  }
  if (result->mvs) {
    j["best_views"] = absl::GetFlag(FLAGS_patchmatch_best_views);
    j["max_cost"] = absl::GetFlag(FLAGS_patchmatch_max_cost);
    j["geometric_consistency"] = absl::GetFlag(FLAGS_geometric_consistency);
    j["add_sparse"] = options.fusion.add_sparse_points;
    j["depth_pixels"] = result->mvs->fusion.depth_pixels;
    j["fused_points"] = result->mvs->fusion.fused_points;
    j["fused_points_capped"] = result->mvs->fusion.points;
    j["max_points"] = options.fusion.max_points;
    j["patchmatch_seconds"] = result->mvs->patchmatch_seconds;
    j["fusion_seconds"] = result->mvs->fusion.seconds;
  }
  if (const std::string dir = absl::GetFlag(FLAGS_ply_dir); !dir.empty()) {
    const std::filesystem::path ply =
        std::filesystem::path(dir) / absl::StrCat(scene_name, "_", views, "v_", result->method, ".ply");
    std::error_code ignored;  // a folder that cannot be made fails the write below, naming the file
    std::filesystem::create_directories(ply.parent_path(), ignored);
    if (const absl::Status written = gaps::write_point_cloud_ply(result->points, ply); !written.ok())
      return fail(written);
    j["ply"] = ply.string();
  }
  j["test_views"] = split->test.size();
  j["test_coverage_mean"] = coverage_sum / split->test.size();
  j["test_coverage_min"] = coverage_min;
  j["seconds"] = seconds;
  j["threads"] = at::get_num_threads();
  j["device"] = device.str();
  if (!result->warnings.empty()) j["warnings"] = result->warnings;
  return j;
}

}  // namespace

int main(int argc, char** argv) {
  absl::ParseCommandLine(argc, argv);
  const std::filesystem::path data(GAPS_DATA_DIR);
  std::vector<std::tuple<std::string, std::filesystem::path, int>> cases;
  for (int n : parse_counts(absl::GetFlag(FLAGS_fern_views))) cases.emplace_back("fern", data / "llff" / "fern", n);
  for (int n : parse_counts(absl::GetFlag(FLAGS_bonsai_views)))
    cases.emplace_back("bonsai", data / "mipnerf360" / "bonsai", n);
  std::ofstream out;
  if (!absl::GetFlag(FLAGS_json).empty()) out.open(absl::GetFlag(FLAGS_json), std::ios::app);
  int failures = 0;
  for (const auto& [name, root, views] : cases) {
    const nlohmann::json j = run_case(name, root, views);
    failures += j.contains("error");
    std::cout << j.dump() << std::endl;
    if (out.is_open()) out << j.dump() << "\n" << std::flush;
  }
  return failures == 0 ? 0 : 1;
}

#include "gs_trainer/run/initial_model.h"

#include <algorithm>
#include <chrono>

#include <ATen/ATen.h>
#include <nlohmann/json.hpp>
#include "absl/strings/match.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_join.h"
#include "common/cli/command_line.h"
#include "common/error_kind.h"
#include "common/image_io.h"
#include "common/ply.h"
#include "common/status_macros.h"
#include "gs_trainer/init/initializer.h"
#include "gs_trainer/run/inputs.h"
#include "gs_trainer/run/mvs_settings.h"
#include "gs_trainer/train/budget.h"

namespace gaps {
namespace {

// The training views as the initialisation reads them: `train` itself, or the same views loaded again at
// o.init_resolution (matched by image name), so that SIFT and the plane sweep can see more pixels than the
// model trains on. The points are in world units either way.
absl::StatusOr<std::vector<TrainingView>> views_for_initialisation(const RunOptions& o,
                                                                   const std::vector<TrainingView>& train,
                                                                   const RunLog& log) {
  if (o.init_resolution == 0 || o.init_resolution == o.resolution || train.empty()) return train;
  GAPS_ASSIGN_OR_RETURN(Scene scene, load_scene_at(o, o.init_resolution));
  std::vector<int> indices;
  for (const auto& v : train) {
    const auto same = std::find_if(scene.cameras.begin(), scene.cameras.end(),
                                   [&](const Camera& c) { return c.name == v.camera.name; });
    if (same == scene.cameras.end())
      return absl::NotFoundError(absl::StrCat("init resolution ", o.init_resolution, ": no image ", v.camera.name));
    indices.push_back(static_cast<int>(same - scene.cameras.begin()));
  }
  GAPS_ASSIGN_OR_RETURN(std::vector<TrainingView> views, load_views(scene, indices, at::kCPU));
  log(absl::StrCat("init: reading the training views at ", views[0].camera.width, "x", views[0].camera.height,
                   " (init resolution ", o.init_resolution, ")"));
  return views;
}

// The training views at twice their size: from o.larger_views_dir (a service job's upload), or the scene at
// half the training resolution; *resolution: the downscale factor they are at, relative to the scene as loaded.
absl::StatusOr<std::vector<TrainingView>> larger_training_views(const RunOptions& o,
                                                                const std::vector<TrainingView>& train,
                                                                const RunLog& log, double* resolution) {
  if (!o.larger_views_dir.empty()) {
    std::vector<TrainingView> views;
    for (const auto& v : train) {
      const std::filesystem::path file = o.larger_views_dir / v.camera.name;
      GAPS_ASSIGN_OR_RETURN(const auto size, read_image_size(file));
      Camera camera = v.camera.resized(size.first, size.second);
      camera.image_path = file;
      GAPS_ASSIGN_OR_RETURN(at::Tensor image, load_camera_image(camera));
      views.push_back({camera, image});
    }
    *resolution = o.resolution / 2.0;
    return views;
  }
  if (o.resolution < 2 || o.resolution % 2 != 0)
    return absl::NotFoundError(absl::StrCat("resolution ", o.resolution, " has no half"));
  RunOptions half = o;
  half.init_resolution = o.resolution / 2;
  *resolution = half.init_resolution;
  return views_for_initialisation(half, train, log);
}

// The views the initialisation reads, the options it runs with and the views' downscale factor: "auto"'s larger
// views where auto_reads_larger_views holds and they can be read, else o's.
struct InitInputs {
  RunOptions options;
  std::vector<TrainingView> views;
  double resolution = 0;
};

absl::StatusOr<InitInputs> initialisation_inputs(const RunOptions& o, const std::vector<TrainingView>& train,
                                                 const RunLog& log) {
  const std::vector<Camera> cameras = cameras_of(train);
  if (auto_reads_larger_views(o, cameras)) {
    double resolution = 0;
    absl::StatusOr<std::vector<TrainingView>> views = larger_training_views(o, train, log, &resolution);
    if (views.ok()) {
      const int side = longest_side(cameras);
      RunOptions larger = o;
      larger.patchmatch.max_image_side = 2 * side;
      larger.sparse.max_image_side = side;
      // Four times the pixels: on a CPU the choice costs minutes, so the way out is named there. No timing is
      // claimed here: the result may come from the cache, and the stages say their own times as they run. A
      // service job (its larger views uploaded) is not told of a flag gaps submit does not take.
      const bool on_cpu = at::Device(o.config.device).is_cpu() && o.larger_views_dir.empty();
      log(absl::StrCat("init: auto: the views face one way, so PatchMatch reads them at twice the training size (",
                       2 * side, " pixels on the longest side) and SIFT at the training size",
                       on_cpu ? absl::StrCat(" (--init-resolution ", o.resolution, " keeps the training views)") : ""));
      return InitInputs{std::move(larger), *std::move(views), resolution};
    }
    log(absl::StrCat("init: auto: no views at twice the training size for PatchMatch (", views.status().message(),
                     "): it reads the training views"));
  }
  GAPS_ASSIGN_OR_RETURN(std::vector<TrainingView> views, views_for_initialisation(o, train, log));
  return InitInputs{o, std::move(views), static_cast<double>(o.init_resolution > 0 ? o.init_resolution : o.resolution)};
}

// Settings only "mvs" reads, given to a run whose points came from another method, would do nothing unseen.
// (The sparse stage's setting is read by every method that triangulates.)
void note_unused_mvs_settings(const RunOptions& o, const std::string& method, const RunLog& log) {
  if (method == "mvs") return;
  const bool triangulated = method == "sweep" || method == "sparse";
  std::vector<std::string> flags;
  const nlohmann::json changed = changed_mvs_settings(o);
  for (const auto& [name, value] : changed.items())
    if (!(triangulated && absl::StartsWith(name, "sparse_"))) flags.push_back(cli::display_name(name));
  if (!flags.empty())
    log(absl::StrCat("init: ", absl::StrJoin(flags, ", "), " not used: the points came from ", method));
}

InitRecord init_record(const std::string& method, const RunOptions& used, double resolution) {
  return {method, resolution, used.patchmatch, used.fusion, used.sparse};
}

// The model training starts from: the Gaussians of a full 3DGS PLY given as --init-ply (every property, so
// that training continues it; its SH brought to the run's degree), or gaussians_from_points of the initial
// points. *record as in initial_points, method "ply-model" for a full model.
absl::StatusOr<GaussianModel> initial_model_of(const RunOptions& o, const Scene& scene,
                                               const std::vector<TrainingView>& train, const RunLog& log,
                                               InitRecord* record) {
  if (o.init == "ply" && !o.init_ply.empty()) {
    // A file a flag names: its faults are input data (exit status 4).
    absl::StatusOr<PlyVertices> vertices = read_ply_vertices(o.init_ply);
    if (!vertices.ok()) return input_data_error(vertices.status());
    if (holds_gaussians(*vertices)) {
      absl::StatusOr<GaussianModel> read = gaussians_from_ply_vertices(*vertices, o.init_ply.string());
      if (!read.ok()) return input_data_error(read.status());
      GaussianModel model = *std::move(read);
      log(absl::StrCat("init: ", o.init_ply.string(), " is a full 3DGS model: ", model.size(), " Gaussians, SH degree ",
                       model.max_sh_degree, ", every property kept"));
      if (model.max_sh_degree != o.config.max_sh_degree)
        log(absl::StrCat("init: SH degree ", model.max_sh_degree, " -> ", o.config.max_sh_degree,
                         " (max_sh_degree): bands ",
                         model.max_sh_degree < o.config.max_sh_degree ? "added as zeros" : "dropped"));
      *record = init_record("ply-model", o, o.resolution);
      return with_sh_degree(std::move(model), o.config.max_sh_degree);
    }
    log(absl::StrCat("init: ", o.init_ply.string(),
                     " is a point cloud (no opacity, scale_*, rot_*): Gaussians made from its points"));
  }
  GAPS_ASSIGN_OR_RETURN(const PointCloud points, initial_points(o, scene, train, log, record));
  log(absl::StrCat("initial points: ", points.xyz.size(0)));
  return gaussians_from_points(points, o.config.max_sh_degree);
}

}  // namespace

absl::StatusOr<PointCloud> initial_points(const RunOptions& o, const Scene& scene,
                                          const std::vector<TrainingView>& train, const RunLog& log, InitRecord* record,
                                          const std::filesystem::path& dense_workspace) {
  if (record) *record = init_record(o.init, o, o.init_resolution > 0 ? o.init_resolution : o.resolution);
  if (o.init == "ply" || o.init == "scene") note_unused_mvs_settings(o, o.init, log);
  if (o.init == "ply") {
    if (o.init_ply.empty()) return usage_error("--init ply needs --init-ply FILE");
    absl::StatusOr<PointCloud> points = read_point_cloud_ply(o.init_ply);
    if (!points.ok()) return input_data_error(points.status());  // a file a flag names: exit status 4
    return points;
  }
  if (o.init == "scene") {
    if (!scene.points) return absl::FailedPreconditionError(absl::StrCat(scene.root.string(), " ships no points"));
    log("warning: initialising from the scene's own points; they may have been reconstructed with the test views");
    return *scene.points;
  }
  GAPS_ASSIGN_OR_RETURN(const InitInputs inputs, initialisation_inputs(o, train, log));
  const RunOptions& used = inputs.options;
  std::vector<Camera> cameras = cameras_of(inputs.views);
  std::vector<at::Tensor> images;
  // On the run's device (views at another init resolution are read to the CPU): it picks PatchMatch's path.
  const at::Device device(o.config.device);
  for (const auto& v : inputs.views) images.push_back(v.image.to(device));
  InitOptions init;
  init.cache_dir = used.init_cache_dir;
  init.should_stop = o.should_stop;
  init.on_progress = stage_progress_lines(log);
  init.random_points = used.random_points;
  init.seed = used.config.seed;
  init.dense_workspace = dense_workspace;
  init.sparse = used.sparse;
  init.patchmatch = used.patchmatch;
  init.fusion = used.fusion;
  // No more fused points than the Gaussians the run may grow to (FusionOptions::max_points says why).
  init.fusion.max_points = gaussian_budget(used.config.max_gaussians, used.config.gaussians_per_variation, train);
  std::string report, method;
  bool from_cache = false;
  auto points = initialize_points(used.init, cameras, images, init, &report, &method, &from_cache);
  if (!report.empty()) log(report);
  if (record) {
    *record = init_record(method, used, inputs.resolution);
    record->from_cache = from_cache;
  }
  // The user's settings, not auto's choices, are what a note on unused settings speaks of.
  if (points.ok()) note_unused_mvs_settings(o, method, log);
  return points;
}

absl::StatusOr<GaussianModel> initial_model(const RunOptions& o, const Scene& scene,
                                            const std::vector<TrainingView>& train, const RunLog& log,
                                            InitRecord* record) {
  const auto start = std::chrono::steady_clock::now();
  GAPS_ASSIGN_OR_RETURN(GaussianModel model, initial_model_of(o, scene, train, log, record));
  record->points = model.size();
  record->seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
  return model;
}

}  // namespace gaps

#include "gs_trainer/pipeline.h"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <fstream>
#include <optional>
#include <set>
#include <type_traits>

#include <ATen/ATen.h>
#include <ATen/core/grad_mode.h>
#include <nlohmann/json.hpp>
#include "absl/strings/match.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_join.h"
#include "common/cli/command_line.h"
#include "common/device.h"
#include "common/error_kind.h"
#include "common/image_io.h"
#include "common/io_util.h"
#include "common/limits.h"
#include "common/ply.h"
#include "common/status_macros.h"
#include "gs_trainer/checkpoint.h"
#include "gs_trainer/eval/lpips.h"
#include "gs_trainer/init/initializer.h"
#include "gs_trainer/model/render.h"
#include "gs_trainer/report.h"
#include "gs_trainer/scene/cameras_json.h"
#include "gs_trainer/scene/run_files.h"
#include "gs_trainer/train/budget.h"
#include "gs_trainer/train/divergence.h"

namespace gaps {
namespace {

using Log = std::function<void(const std::string&)>;

// Loss and parameters are checked for finiteness this often (one device synchronisation each time).
constexpr int kDivergenceCheckEvery = 10;

absl::StatusOr<std::vector<TrainingView>> load_views(const Scene& scene, const std::vector<int>& indices,
                                                     const at::Device& device) {
  std::vector<TrainingView> views;
  for (int i : indices) {
    absl::StatusOr<at::Tensor> image = load_camera_image(scene.cameras[i]);
    if (!image.ok()) return input_data_error(image.status());
    views.push_back({scene.cameras[i], image->to(device)});
  }
  return views;
}

absl::StatusOr<Scene> load_scene_at(const RunOptions& o, int resolution) {
  SceneLoadOptions load;
  load.resolution = resolution;
  absl::StatusOr<Scene> scene = load_scene(o.scene_dir, load);
  if (!scene.ok()) return input_data_error(scene.status());
  return scene;
}

// The protocol's split of the scene for o.views; asking for more views than there are is a usage error
// that says how many there are.
absl::StatusOr<Split> protocol_split(const Scene& scene, int views) {
  const int images = static_cast<int>(scene.cameras.size());
  absl::StatusOr<Split> split = benchmark_split(images, views);
  if (split.ok()) return split;
  constexpr int kHold = 8;  // benchmark_split's: every 8th image is a test view
  const int test = (images + kHold - 1) / kHold;
  const int available = images - test;
  if (views <= available || available <= 0) return input_data_error(split.status());
  return usage_error(absl::StrCat(views, " training views asked for, but ", scene.root.string(), " has ", available,
                                  " besides its ", test, " test views (", images, " images, every ", kHold,
                                  "th held out): ask for at most ", available, " (0: all)"));
}

// out_dir and the folders above it, as a status instead of the exception of create_directories.
absl::Status make_folder(const std::filesystem::path& dir) {
  std::error_code ec;
  std::filesystem::create_directories(dir, ec);
  if (ec || !std::filesystem::is_directory(dir))
    return absl::PermissionDeniedError(
        absl::StrCat(dir.string(), ": cannot create the folder (", ec ? ec.message() : "not a folder", ")"));
  return absl::OkStatus();
}

// The training views as the initialisation reads them: `train` itself, or the same views loaded again at
// o.init_resolution (matched by image name), so that SIFT and the plane sweep can see more pixels than the
// model trains on. The points are in world units either way.
absl::StatusOr<std::vector<TrainingView>> views_for_initialisation(const RunOptions& o,
                                                                   const std::vector<TrainingView>& train,
                                                                   const Log& log) {
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

// The longest side of any of these cameras' images, in pixels (0 for none).
int longest_side(const std::vector<Camera>& cameras) {
  int side = 0;
  for (const Camera& c : cameras) side = std::max({side, c.width, c.height});
  return side;
}

std::vector<Camera> cameras_of(const std::vector<TrainingView>& views) {
  std::vector<Camera> cameras;
  for (const auto& v : views) cameras.push_back(v.camera);
  return cameras;
}

// The training views at twice their size: from o.larger_views_dir (a service job's upload), or the scene at
// half the training resolution; *resolution: the downscale factor they are at, relative to the scene as loaded.
absl::StatusOr<std::vector<TrainingView>> larger_training_views(const RunOptions& o,
                                                                const std::vector<TrainingView>& train, const Log& log,
                                                                double* resolution) {
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
                                                 const Log& log) {
  const std::vector<Camera> cameras = cameras_of(train);
  if (auto_reads_larger_views(o, cameras)) {
    double resolution = 0;
    absl::StatusOr<std::vector<TrainingView>> views = larger_training_views(o, train, log, &resolution);
    if (views.ok()) {
      const int side = longest_side(cameras);
      RunOptions larger = o;
      larger.patchmatch.max_image_side = 2 * side;
      larger.sparse.max_image_side = side;
      // On the CPU PatchMatch then takes about four times as long (fern 3 views: 245 s against 64 s on 2 cores).
      const bool on_cpu = at::Device(o.config.device).is_cpu();
      log(absl::StrCat("init: auto: the views face one way, so PatchMatch reads them at twice the training size (",
                       2 * side, " pixels on the longest side) and SIFT at the training size",
                       on_cpu ? "; on the CPU that takes about four times as long (--init-resolution " : "",
                       on_cpu ? absl::StrCat(o.resolution, " keeps the training views)") : ""));
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
void note_unused_mvs_settings(const RunOptions& o, const std::string& method, const Log& log) {
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

// *record (if given): what made the points (InitRecord). dense_workspace: InitOptions::dense_workspace.
absl::StatusOr<PointCloud> initial_points(const RunOptions& o, const Scene& scene,
                                          const std::vector<TrainingView>& train, const Log& log,
                                          InitRecord* record = nullptr,
                                          const std::filesystem::path& dense_workspace = {}) {
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

// The model training starts from: the Gaussians of a full 3DGS PLY given as --init-ply (every property, so
// that training continues it; its SH brought to the run's degree), or gaussians_from_points of the initial
// points. *record as in initial_points, method "ply-model" for a full model.
absl::StatusOr<GaussianModel> initial_model_of(const RunOptions& o, const Scene& scene,
                                               const std::vector<TrainingView>& train, const Log& log,
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

// initial_model_of, with the count and the wall-clock seconds in *record.
absl::StatusOr<GaussianModel> initial_model(const RunOptions& o, const Scene& scene,
                                            const std::vector<TrainingView>& train, const Log& log,
                                            InitRecord* record) {
  const auto start = std::chrono::steady_clock::now();
  GAPS_ASSIGN_OR_RETURN(GaussianModel model, initial_model_of(o, scene, train, log, record));
  record->points = model.size();
  record->seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
  return model;
}

absl::Status write_json(const std::filesystem::path& path, const nlohmann::json& j) {
  return write_file_bytes(path, j.dump(2) + "\n");
}

// `failure` empty: a finished run; otherwise the run's status ("diverged") and error, without final metrics.
absl::Status write_metrics(const RunOptions& o, const RunResult& r, const std::string& failure = "",
                           const std::string& error = "") {
  nlohmann::json j;
  j["status"] = failure.empty() ? "ok" : failure;
  if (!failure.empty()) j["error"] = error;
  j["psnr"] = r.metrics.psnr;
  j["ssim"] = r.metrics.ssim;
  j["lpips"] = r.metrics.lpips ? nlohmann::json(*r.metrics.lpips) : nlohmann::json(nullptr);
  j["num_gaussians"] = r.num_gaussians;
  j["max_gaussians"] = r.max_gaussians;
  j["train_seconds"] = r.train_seconds;
  j["eval_every"] = o.eval_every;
  j["curve"] = r.curve;
  j["peak_memory"] = r.peak_memory;
  j["generator_seconds"] = r.generator_seconds ? nlohmann::json(*r.generator_seconds) : nlohmann::json(nullptr);
  j.update(run_configuration_json(o, r));
  if (!failure.empty()) {
    for (const char* key : {"psnr", "ssim", "lpips"}) j[key] = nullptr;
  }
  for (size_t i = 0; i < r.per_view.size(); ++i) {
    const ImageMetrics& v = r.per_view[i];
    j["per_view"].push_back({{"image", i < r.per_view_images.size() ? r.per_view_images[i] : ""},
                             {"psnr", v.psnr},
                             {"ssim", v.ssim},
                             {"lpips", v.lpips ? nlohmann::json(*v.lpips) : nlohmann::json(nullptr)}});
  }
  return write_json(o.out_dir / "metrics.json", j);
}

// metrics.json (see write_metrics) and, when asked for, report.html.
absl::Status write_outputs(const RunOptions& o, const RunResult& r, const std::vector<TrainingView>& test,
                           const std::string& failure = "", const std::string& error = "") {
  GAPS_RETURN_IF_ERROR(write_metrics(o, r, failure, error));
  if (o.html_report) GAPS_RETURN_IF_ERROR(write_run_report(o.out_dir, test));
  return absl::OkStatus();
}

// What run_init_only and run_pipeline both start from: the scene split by the protocol (its description
// logged) and the training views loaded.
struct LoadedScene {
  Scene scene;
  Split split;
  std::string summary;
  std::vector<TrainingView> train;
};

absl::StatusOr<LoadedScene> load_scene_and_training_views(const RunOptions& o, const at::Device& device,
                                                          const Log& log) {
  LoadedScene loaded;
  GAPS_ASSIGN_OR_RETURN(loaded.scene, load_scene_at(o, o.resolution));
  GAPS_ASSIGN_OR_RETURN(loaded.split, protocol_split(loaded.scene, o.views));
  loaded.summary = describe(loaded.scene, loaded.split);
  log(loaded.summary);
  GAPS_ASSIGN_OR_RETURN(loaded.train, load_views(loaded.scene, loaded.split.train, device));
  return loaded;
}

// o with "auto"'s budget where it holds for these training views (with_auto_budget), said in the log.
RunOptions budgeted_options(const RunOptions& o, const std::vector<TrainingView>& train, const Log& log) {
  RunOptions used = with_auto_budget(o, cameras_of(train));
  if (used.config.gaussians_per_variation == kAutoLargerViewsGaussiansPerVariation &&
      o.config.gaussians_per_variation < 0)
    log(absl::StrCat("budget: auto: the views face one way, so ", used.config.gaussians_per_variation,
                     " Gaussians per unit of their total variation (--gaussians-per-variation sets another)"));
  return used;
}

// cameras.json (gs_trainer/scene/cameras_json.h): the training views, then the test views.
absl::Status write_run_cameras(const std::filesystem::path& path, const std::vector<TrainingView>& train,
                               const std::vector<TrainingView>& test) {
  std::vector<CameraRecord> cameras;
  for (const TrainingView& v : train) cameras.push_back({v.camera, "train"});
  for (const TrainingView& v : test) cameras.push_back({v.camera, "test"});
  return write_cameras_json(path, cameras);
}

// Nothing when the run measures without LPIPS (it is then reported as null).
absl::StatusOr<std::optional<Lpips>> run_lpips(const RunOptions& o, const at::Device& device) {
  absl::StatusOr<std::optional<Lpips>> lpips = load_lpips(o.lpips_weights, o.lpips_backbone, device);
  if (!lpips.ok()) return input_data_error(lpips.status());
  return lpips;
}

}  // namespace

absl::Status check_scene(const RunOptions& o) {
  if (o.init != "ply" && o.init != "scene" && !is_init_method(o.init))
    return usage_error(
        absl::StrCat("--init ", o.init, ": unknown; use auto, mvs, sweep, sparse, random, scene or ply"));
  if (o.init == "ply") {
    if (o.init_ply.empty()) return usage_error("initialisation 'ply' needs a point cloud file (--init-ply FILE)");
    std::error_code ec;
    if (!std::filesystem::is_regular_file(o.init_ply, ec))
      return input_data_error(absl::NotFoundError(absl::StrCat(o.init_ply.string(), ": point cloud file not found")));
  }
  if (o.resolution <= 0) return usage_error(absl::StrCat("resolution must be positive, got ", o.resolution));
  if (absl::Status s = check_gaussian_count("random_points", o.random_points); !s.ok()) return usage_error(s.message());
  if (o.init_resolution < 0)
    return usage_error(
        absl::StrCat("init resolution must be >= 0 (0: the training resolution), got ", o.init_resolution));
  if (absl::Status s = validate_mvs_settings(o); !s.ok()) return usage_error(s.message());
  GAPS_ASSIGN_OR_RETURN(const Scene scene, load_scene_at(o, o.resolution));
  GAPS_RETURN_IF_ERROR(protocol_split(scene, o.views).status());
  if (o.init == "scene" && !scene.points)
    return usage_error(absl::StrCat(scene.root.string(), " ships no points to initialise from; use another --init"));
  return absl::OkStatus();
}

std::vector<std::string> run_output_names() {
  return {
      "point_cloud.ply", "cameras.json",         "metrics.json",        "report.html",           "renders",
      "phases.json",     kPseudoViewsFolder,     "checkpoint",          "checkpoint.old",        "checkpoint.partial",
      "points.ply",      "sparse/0/cameras.txt", "sparse/0/images.txt", "sparse/0/points3D.txt", "dense"};
}

namespace {

// One table for both directions, so that a setting cannot be written without being read back. The names
// are the flags' (and gaps.v1.InitSettings's fields).
// Options: RunOptions or const RunOptions.
template <typename Options, typename Visit>
void visit_mvs_settings(Options& o, Visit&& visit) {
  visit("patchmatch_best_views", o.patchmatch.best_views);
  visit("patchmatch_max_cost", o.patchmatch.max_cost);
  visit("patchmatch_iterations", o.patchmatch.iterations);
  visit("patchmatch_max_image_side", o.patchmatch.max_image_side);
  visit("patchmatch_geometric_consistency", o.patchmatch.geometric_consistency);
  visit("fusion_min_views", o.fusion.min_views);
  visit("fusion_max_normal_error", o.fusion.max_normal_error_deg);
  visit("fusion_add_sparse", o.fusion.add_sparse_points);
  visit("sparse_max_image_side", o.sparse.max_image_side);
}

}  // namespace

nlohmann::json mvs_settings_json(const RunOptions& options) {
  nlohmann::json j = nlohmann::json::object();
  visit_mvs_settings(options, [&](const char* name, const auto& value) { j[name] = value; });
  return j;
}

nlohmann::json changed_mvs_settings(const RunOptions& options) {
  const nlohmann::json defaults = mvs_settings_json(RunOptions{}), settings = mvs_settings_json(options);
  nlohmann::json changed = nlohmann::json::object();
  for (const auto& [name, value] : settings.items())
    if (value != defaults.at(name)) changed[name] = value;
  return changed;
}

absl::Status read_mvs_settings(const nlohmann::json& settings, RunOptions& options) {
  if (!settings.is_object()) return absl::InvalidArgumentError("init settings: not a JSON object");
  const nlohmann::json known = mvs_settings_json(options);
  for (const auto& [name, value] : settings.items())
    if (!known.contains(name)) return absl::InvalidArgumentError(absl::StrCat("init settings: unknown '", name, "'"));
  absl::Status status;
  visit_mvs_settings(options, [&](const char* name, auto& value) {
    if (!status.ok() || !settings.contains(name)) return;
    try {
      value = settings[name].get<std::remove_reference_t<decltype(value)>>();
    } catch (const std::exception& e) {
      status = absl::InvalidArgumentError(absl::StrCat("init settings: ", name, ": ", e.what()));
    }
  });
  return status;
}

bool auto_reads_larger_views(const RunOptions& o, const std::vector<Camera>& train) {
  if (o.init != "auto" || train.empty() || o.init_resolution != 0 ||
      o.sparse.max_image_side != SparseOptions{}.max_image_side ||
      o.patchmatch.max_image_side != PatchMatchOptions{}.max_image_side)
    return false;
  return 2 * longest_side(train) <= kAutoLargerViewsMaxSide && !views_surround_scene(train);
}

RunOptions with_auto_budget(const RunOptions& options, const std::vector<Camera>& train) {
  RunOptions used = options;
  double& density = used.config.gaussians_per_variation;
  if (density < 0)
    density = options.config.max_gaussians == 0 && auto_reads_larger_views(options, train)
                  ? kAutoLargerViewsGaussiansPerVariation
                  : kDefaultGaussiansPerVariation;
  return used;
}

absl::Status validate_mvs_settings(const RunOptions& options) {
  if (absl::Status s = validate_patchmatch_options(options.patchmatch); !s.ok())
    return absl::InvalidArgumentError(absl::StrCat("PatchMatch: ", s.message()));
  if (absl::Status s = validate_fusion_options(options.fusion); !s.ok())
    return absl::InvalidArgumentError(absl::StrCat("fusion: ", s.message()));
  if (absl::Status s = validate_sparse_options(options.sparse); !s.ok())
    return absl::InvalidArgumentError(absl::StrCat("sparse: ", s.message()));
  return absl::OkStatus();
}

nlohmann::json run_configuration_json(const RunOptions& o, const RunResult& r) {
  nlohmann::json j;
  j["iterations"] = r.config.iterations;
  j["views"] = o.views;
  j["resolution"] = o.resolution;
  j["device"] = r.config.device;
  j["seed"] = r.config.seed;
  j["init"] = o.init;
  j["init_method"] = r.init.method;
  // A downscale factor of the scene, written as an integer where it is one (0.5: a service job's larger views).
  const double init_resolution = r.init.resolution > 0 ? r.init.resolution : o.resolution;
  if (init_resolution == std::floor(init_resolution))
    j["init_resolution"] = static_cast<int>(init_resolution);
  else
    j["init_resolution"] = init_resolution;
  RunOptions used = o;  // the initialisation's settings as it ran them
  used.patchmatch = r.init.patchmatch;
  used.fusion = r.init.fusion;
  used.sparse = r.init.sparse;
  j["init_options"] = mvs_settings_json(used);
  j["init_points"] = r.init.points;
  j["init_seconds"] = r.init.seconds;
  j["init_from_cache"] = r.init.from_cache;
  j["random_points"] = o.random_points;
  j["variant"] = variant_name(o.variant);
  if (o.variant != Variant::kVanilla) {
    j["phases"] = r.phases;
    j["phases_skipped"] = r.phases_skipped;
    j["degraded"] = r.degraded();
    j["gaps"] = r.gaps;
    j["generator"] = o.generator ? o.generator->name() : "";
  }
  j["scene"] = o.scene_dir.string();
  j["config"] = r.config;
  return j;
}

namespace {

// The trainer and, for the paper's variants, the method driving it, from the initial points to the end of
// training. The method refers to the trainer, hence neither copied nor moved.
class TrainingRun {
 public:
  TrainingRun(const RunOptions& o, const Log& log, const GaussianModel& initial, std::vector<TrainingView> train,
              const at::Device& device)
      : o_(o),
        log_(log),
        references_(train),
        trainer_(initial.to(device), std::move(train), o.config),
        guard_(kDivergenceCheckEvery, o.config.iterations) {
    const int64_t budget = trainer_.config().max_gaussians;
    if (o.config.max_gaussians == 0 && o.config.gaussians_per_variation > 0)
      log(absl::StrCat("automatic budget: ", budget, " Gaussians (", o.config.gaussians_per_variation,
                       " per unit of the training views' total variation)"));
    if (budget > 0 && initial.size() >= budget)
      log(absl::StrCat("warning: the ", initial.size(), " initial Gaussians already fill the budget of ", budget,
                       " Gaussians, so densification will add none (raise --gaussians-per-variation, set "
                       "--max-gaussians, or start from fewer points)"));
  }
  TrainingRun(const TrainingRun&) = delete;
  TrainingRun& operator=(const TrainingRun&) = delete;

  const Trainer& trainer() const { return trainer_; }
  std::optional<double> generator_seconds() const {
    return generator_ ? std::optional<double>(generator_->seconds()) : std::nullopt;
  }
  // Wall-clock training time, without the curve's evaluations and the checkpoints, including a resumed run's
  // earlier part.
  double train_seconds() const { return seconds_since_start(std::chrono::steady_clock::now()); }
  // The evaluations so far (a resumed run's earlier ones first).
  const std::vector<CurvePoint>& curve() const { return curve_; }

  // The method's options as used: n_active resolved from the training views' layout when 0.
  GapsConfig effective_gaps() const {
    GapsConfig gaps = o_.gaps;
    gaps.n_active = n_active_for(o_.gaps, views_surround_scene(cameras_of(references_)));
    return gaps;
  }

  // The paper's method, with `gaps` (effective_gaps()), on top of the trainer; nothing for the vanilla variant.
  absl::Status attach_method(const GapsConfig& gaps) {
    if (o_.variant == Variant::kVanilla) return absl::OkStatus();
    if (!o_.generator)
      return absl::InvalidArgumentError(
          absl::StrCat("variant ", variant_name(o_.variant), " needs a generator backend"));
    if (o_.gaps.n_active == 0)
      log_(absl::StrCat("pseudo-views per phase: ", gaps.n_active, " (the training views ",
                        gaps.n_active == kNActiveMip360 ? "surround the scene" : "face one way", ")"));
    generator_.emplace(o_.generator);
    method_.emplace(trainer_, &*generator_, references_, gaps, o_.variant, o_.config.seed);
    method_->set_inspection_dir(o_.out_dir / kPseudoViewsFolder);
    method_->set_phase_observer([this](const std::string& event, const nlohmann::json& entry) {
      // The state before the phase: a resumed run repeats the phase, then goes on.
      if (event == "started") save_checkpoint_and_tell();
      if (event != "started") log_generator_notes(entry);
      if (o_.on_phase) o_.on_phase(event, entry);
    });
    log_(absl::StrCat("method: ", variant_name(o_.variant), " with generator ", o_.generator->name()));
    return absl::OkStatus();
  }

  // Goes on from the checkpoint in o.checkpoint_dir, if there is one, with the curve and training time
  // it kept.
  absl::Status resume() {
    if (o_.checkpoint_dir.empty()) return absl::OkStatus();
    nlohmann::json kept;
    const absl::StatusOr<int> resumed = load_checkpoint(o_.checkpoint_dir, trainer_, method(), &kept);
    if (absl::IsNotFound(resumed.status())) return absl::OkStatus();
    if (!resumed.ok()) return resumed.status();
    try {
      curve_ = kept.value("curve", std::vector<CurvePoint>());
      seconds_before_ = kept.value("train_seconds", 0.0);
    } catch (const std::exception& e) {
      return absl::DataLossError(absl::StrCat(o_.checkpoint_dir.string(), ": run state: ", e.what()));
    }
    log_(absl::StrCat("resumed from the checkpoint at iteration ", *resumed));
    return absl::OkStatus();
  }

  // Trains to the last iteration unless stopped (should_stop) or diverged; every o.eval_every iterations
  // the test views are evaluated into the curve.
  absl::Status train(const ProgressCallback& on_progress, const std::vector<TrainingView>& test, const Lpips* lpips) {
    start_ = last_save_ = std::chrono::steady_clock::now();
    if (o_.on_training_started) o_.on_training_started();
    return trainer_.run(on_progress, 10, [&] { return monitored_step(test, lpips); });
  }

  // After train(): a stopped run (cancelled, or its service shutting down) leaves its state for a later
  // resume; the method's phases go to phases.json.
  absl::Status keep_state(const absl::Status& trained) {
    if (absl::IsCancelled(trained)) save_checkpoint_and_tell();
    if (!method_) return absl::OkStatus();
    const absl::Status inspected = method_->finish_inspection();
    GAPS_RETURN_IF_ERROR(write_json(o_.out_dir / "phases.json", method_->phase_log()));
    return inspected;
  }

  // Phases run and skipped so far, into *result.
  void count_phases(RunResult* result) const {
    if (!method_) return;
    for (const auto& entry : method_->phase_log()) {
      ++result->phases;
      if (entry.value("skipped", false)) ++result->phases_skipped;
    }
  }

 private:
  GapsTraining* method() { return method_ ? &*method_ : nullptr; }

  // What the generator could not honour of the job's controls, in the run log the first time it comes up
  // (phases.json keeps every phase's notes).
  void log_generator_notes(const nlohmann::json& entry) {
    if (!entry.contains("generator_notes")) return;
    for (const auto& note : entry["generator_notes"]) {
      if (logged_notes_.insert(note.get<std::string>()).second)
        log_(absl::StrCat("generator note (phase ", entry.value("phase", -1), "): ", note.get<std::string>()));
    }
  }

  // Every checkpoint_every iterations, or checkpoint_every_seconds after the last save (or the start).
  bool checkpoint_due(int it) const {
    if (o_.checkpoint_every > 0 && it % o_.checkpoint_every == 0) return true;
    return o_.checkpoint_every_seconds > 0 &&
           std::chrono::duration<double>(std::chrono::steady_clock::now() - last_save_).count() >=
               o_.checkpoint_every_seconds;
  }

  // The training state to o.checkpoint_dir (when set); a failure costs the checkpoint only, with a warning.
  void save_checkpoint_and_tell() {
    if (o_.checkpoint_dir.empty()) return;
    // A resumed run does not redo the phases before its checkpoint, so their images must be on disk first; a
    // failed write is the next phase's (or the run end's) error.
    if (method_) (void)method_->finish_inspection();
    const auto save_start = std::chrono::steady_clock::now();
    last_save_ = save_start;
    const nlohmann::json kept = {{"curve", curve_}, {"train_seconds", seconds_since_start(save_start)}};
    const absl::Status saved = save_checkpoint(o_.checkpoint_dir, trainer_, method(), kept);
    excluded_seconds_ += std::chrono::duration<double>(std::chrono::steady_clock::now() - save_start).count();
    if (!saved.ok())
      log_(absl::StrCat("warning: checkpoint not written: ", saved.message()));
    else if (o_.on_checkpoint)
      o_.on_checkpoint(trainer_.iteration());
  }

  double seconds_since_start(std::chrono::steady_clock::time_point t) const {
    return seconds_before_ + std::chrono::duration<double>(t - start_).count() - excluded_seconds_;
  }

  // One iteration of the method (or of the trainer alone), unless should_stop says otherwise.
  absl::StatusOr<at::Tensor> next_step() {
    if (o_.should_stop && o_.should_stop())
      return absl::CancelledError(absl::StrCat("stopped at iteration ", trainer_.iteration()));
    if (method_) return method_->step();
    return trainer_.step();
  }

  // The step, the divergence guard, at the curve's iterations an evaluation whose time is left out of the
  // training time (the last iteration's is the run's final evaluation), and the periodic checkpoint.
  absl::StatusOr<at::Tensor> monitored_step(const std::vector<TrainingView>& test, const Lpips* lpips) {
    GAPS_ASSIGN_OR_RETURN(at::Tensor loss, next_step());
    const int it = trainer_.iteration();
    GAPS_RETURN_IF_ERROR(guard_.observe(it, loss, trainer_.model()));
    if (it < o_.config.iterations) {
      GAPS_RETURN_IF_ERROR(evaluate_for_curve(it, loss, test, lpips));
      if (checkpoint_due(it)) save_checkpoint_and_tell();
    }
    return loss;
  }

  absl::Status evaluate_for_curve(int it, const at::Tensor& loss, const std::vector<TrainingView>& test,
                                  const Lpips* lpips) {
    if (o_.eval_every <= 0 || it % o_.eval_every != 0) return absl::OkStatus();
    (void)loss.item<double>();  // the queued training work belongs to the training time
    const auto eval_start = std::chrono::steady_clock::now();
    GAPS_ASSIGN_OR_RETURN(const std::vector<ImageMetrics> views,
                          evaluate_views(trainer_.model(), test, o_.config.background, lpips, {}));
    GAPS_ASSIGN_OR_RETURN(const ImageMetrics average, average_metrics(views));
    curve_.push_back({it, seconds_since_start(eval_start), average, trainer_.model().size()});
    excluded_seconds_ += std::chrono::duration<double>(std::chrono::steady_clock::now() - eval_start).count();
    return absl::OkStatus();
  }

  const RunOptions& o_;
  const Log& log_;
  const std::vector<TrainingView> references_;  // the training views as loaded, for the method
  Trainer trainer_;
  std::optional<TimedGenerator> generator_;
  std::optional<GapsTraining> method_;
  std::set<std::string> logged_notes_;
  DivergenceGuard guard_;
  std::vector<CurvePoint> curve_;
  std::chrono::steady_clock::time_point start_;
  std::chrono::steady_clock::time_point last_save_;  // of the last checkpoint, or the start
  double seconds_before_ = 0.0;                      // training time of a resumed run before its checkpoint
  // Spent since start_ on the curve's evaluations and on checkpoints: not training time.
  double excluded_seconds_ = 0.0;
};

// The run's final evaluation on the test views: per view (renders written when asked for), averaged, and as
// the curve's last point.
absl::Status evaluate_final(const RunOptions& o, const GaussianModel& model, const std::vector<TrainingView>& test,
                            const Lpips* lpips, RunResult* result) {
  GAPS_ASSIGN_OR_RETURN(result->per_view,
                        evaluate_views(model, test, o.config.background, lpips,
                                       o.save_renders ? o.out_dir / "renders" : std::filesystem::path()));
  GAPS_ASSIGN_OR_RETURN(result->metrics, average_metrics(result->per_view));
  result->per_view_images.clear();
  for (const TrainingView& v : test) result->per_view_images.push_back(v.camera.name);
  if (o.eval_every > 0)
    result->curve.push_back({o.config.iterations, result->train_seconds, result->metrics, result->num_gaussians});
  return absl::OkStatus();
}

}  // namespace

absl::StatusOr<std::vector<ImageMetrics>> evaluate_views(const GaussianModel& model,
                                                         const std::vector<TrainingView>& views, double background,
                                                         const Lpips* lpips, const std::filesystem::path& render_dir) {
  at::AutoGradMode no_grad(false);
  std::vector<ImageMetrics> out;
  RenderOptions options;
  options.background = at::full({3}, background, model.means.options());
  for (const auto& v : views) {
    const at::Tensor rgb = render(model, v.camera, options).rgb.clamp(0.0, 1.0);
    out.push_back(evaluate_image(rgb, v.image, lpips));
    if (!render_dir.empty()) {
      GAPS_RETURN_IF_ERROR(make_folder(render_dir));
      GAPS_RETURN_IF_ERROR(
          write_png(render_dir / (std::filesystem::path(v.camera.name).stem().string() + ".png"), rgb.to(at::kCPU)));
    }
  }
  return out;
}

absl::Status run_init_only(const RunOptions& o, const Log& log) {
  GAPS_RETURN_IF_ERROR(check_device(o.config.device));
  GAPS_RETURN_IF_ERROR(check_scene(o));
  GAPS_ASSIGN_OR_RETURN(const LoadedScene loaded, load_scene_and_training_views(o, at::Device(o.config.device), log));
  const RunOptions used = budgeted_options(o, loaded.train, log);
  InitRecord record;
  GAPS_ASSIGN_OR_RETURN(const PointCloud points,
                        initial_points(used, loaded.scene, loaded.train, log, &record, o.out_dir / "dense"));
  GAPS_RETURN_IF_ERROR(make_folder(o.out_dir));
  GAPS_RETURN_IF_ERROR(write_point_cloud_ply(points, o.out_dir / "points.ply"));
  GAPS_RETURN_IF_ERROR(write_init_as_colmap(o.out_dir / "sparse" / "0", cameras_of(loaded.train), points));
  log(absl::StrCat(points.xyz.size(0), " points written to ", (o.out_dir / "points.ply").string(), " and ",
                   (o.out_dir / "sparse" / "0").string()));
  if (record.method == "mvs")
    log(absl::StrCat("the PatchMatch depth and normal maps and the fused cloud: COLMAP dense workspace in ",
                     (o.out_dir / "dense").string()));
  return absl::OkStatus();
}

absl::StatusOr<RunResult> run_pipeline(const RunOptions& o, const ProgressCallback& on_progress, const Log& log) {
  GAPS_RETURN_IF_ERROR(check_device(o.config.device));
  GAPS_RETURN_IF_ERROR(check_scene(o));
  const at::Device device(o.config.device);
  GAPS_ASSIGN_OR_RETURN(const std::optional<Lpips> lpips, run_lpips(o, device));
  const Lpips* lpips_model = lpips ? &*lpips : nullptr;
  GAPS_ASSIGN_OR_RETURN(LoadedScene loaded, load_scene_and_training_views(o, device, log));
  GAPS_ASSIGN_OR_RETURN(const std::vector<TrainingView> test, load_views(loaded.scene, loaded.split.test, device));
  RunResult result;
  result.summary = loaded.summary;
  const RunOptions used = budgeted_options(o, loaded.train, log);
  GAPS_ASSIGN_OR_RETURN(const GaussianModel initial,
                        initial_model(used, loaded.scene, loaded.train, log, &result.init));

  GAPS_RETURN_IF_ERROR(make_folder(o.out_dir));
  GAPS_RETURN_IF_ERROR(write_run_cameras(o.out_dir / "cameras.json", loaded.train, test));
  const PeakMemoryMeter memory(device);
  TrainingRun run(used, log, initial, std::move(loaded.train), device);
  result.max_gaussians = run.trainer().config().max_gaussians;
  result.config = run.trainer().config();
  result.gaps = run.effective_gaps();
  GAPS_RETURN_IF_ERROR(run.attach_method(result.gaps));
  GAPS_RETURN_IF_ERROR(run.resume());
  const absl::Status trained = run.train(on_progress, test, lpips_model);
  GAPS_RETURN_IF_ERROR(run.keep_state(trained));
  result.curve = run.curve();

  result.train_seconds = run.train_seconds();
  result.num_gaussians = run.trainer().model().size();
  result.peak_memory = memory.read();
  result.generator_seconds = run.generator_seconds();
  run.count_phases(&result);
  if (result.degraded())
    log(absl::StrCat("warning: degraded run: ", result.phases_skipped, " of ", result.phases,
                     " diffusion phases were skipped (no generator answered); it trained on fewer pseudo-views "
                     "than the method asks for"));
  // Whatever happened, keep what was computed.
  GAPS_RETURN_IF_ERROR(save_gaussians_ply(run.trainer().model(), o.out_dir / "point_cloud.ply"));
  if (is_divergence(trained)) {
    log(std::string(trained.message()));
    GAPS_RETURN_IF_ERROR(write_outputs(o, result, test, "diverged", std::string(trained.message())));
  }
  GAPS_RETURN_IF_ERROR(trained);
  GAPS_RETURN_IF_ERROR(evaluate_final(o, run.trainer().model(), test, lpips_model, &result));
  result.peak_memory = memory.read();
  GAPS_RETURN_IF_ERROR(write_outputs(o, result, test));
  return result;
}

}  // namespace gaps

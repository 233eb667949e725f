#include "gs_trainer/pipeline.h"

#include <algorithm>
#include <chrono>
#include <fstream>

#include <ATen/ATen.h>
#include <ATen/core/grad_mode.h>
#include <nlohmann/json.hpp>
#include "absl/strings/str_cat.h"
#include "common/image_io.h"
#include "common/ply.h"
#include "common/status_macros.h"
#include "gs_trainer/checkpoint.h"
#include "gs_trainer/eval/lpips.h"
#include "gs_trainer/init/initializer.h"
#include "gs_trainer/model/render.h"
#include "gs_trainer/report.h"
#include "gs_trainer/train/divergence.h"

namespace gaps {
namespace {

// Loss and parameters are checked for finiteness this often (one device synchronisation each time).
constexpr int kDivergenceCheckEvery = 10;

absl::StatusOr<std::vector<TrainingView>> load_views(const Scene& scene, const std::vector<int>& indices,
                                                     const at::Device& device) {
  std::vector<TrainingView> views;
  for (int i : indices) {
    GAPS_ASSIGN_OR_RETURN(at::Tensor image, load_camera_image(scene.cameras[i]));
    views.push_back({scene.cameras[i], image.to(device)});
  }
  return views;
}

// The training views as the initialisation reads them: `train` itself, or the same views loaded again at
// o.init_resolution (matched by image name), so that SIFT and the plane sweep can see more pixels than the
// model trains on. The points are in world units either way.
absl::StatusOr<std::vector<TrainingView>> views_for_initialisation(const RunOptions& o,
                                                                   const std::vector<TrainingView>& train,
                                                                   const std::function<void(const std::string&)>& log) {
  if (o.init_resolution < 0)
    return absl::InvalidArgumentError(
        absl::StrCat("init resolution must be >= 0 (0: the training resolution), got ", o.init_resolution));
  if (o.init_resolution == 0 || o.init_resolution == o.resolution || train.empty()) return train;
  SceneLoadOptions load;
  load.resolution = o.init_resolution;
  GAPS_ASSIGN_OR_RETURN(Scene scene, load_scene(o.scene_dir, load));
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

// *method_used (if given): the method that made the points (o.init, "auto" resolved, fallbacks taken).
absl::StatusOr<PointCloud> initial_points(const RunOptions& o, const Scene& scene,
                                          const std::vector<TrainingView>& train,
                                          const std::function<void(const std::string&)>& log,
                                          std::string* method_used = nullptr) {
  if (method_used) *method_used = o.init;
  if (o.init == "ply") {
    if (o.init_ply.empty()) return absl::InvalidArgumentError("--init ply needs --init-ply FILE");
    return read_point_cloud_ply(o.init_ply);
  }
  if (o.init == "scene") {
    if (!scene.points) return absl::FailedPreconditionError(absl::StrCat(scene.root.string(), " ships no points"));
    log("warning: initialising from the scene's own points; they may have been reconstructed with the test views");
    return *scene.points;
  }
  std::vector<Camera> cameras;
  std::vector<at::Tensor> images;
  GAPS_ASSIGN_OR_RETURN(const std::vector<TrainingView> views, views_for_initialisation(o, train, log));
  for (const auto& v : views) {
    cameras.push_back(v.camera);
    images.push_back(v.image);
  }
  InitOptions init;
  init.cache_dir = o.init_cache_dir;
  init.random_points = o.random_points;
  init.seed = o.config.seed;
  std::string report;
  auto points = initialize_points(o.init, cameras, images, init, &report, method_used);
  if (!report.empty()) log(report);
  return points;
}

absl::Status write_json(const std::filesystem::path& path, const nlohmann::json& j) {
  std::ofstream f(path);
  f << j.dump(2) << "\n";
  if (!f) return absl::DataLossError(absl::StrCat(path.string(), ": write failed"));
  return absl::OkStatus();
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
  j["iterations"] = o.config.iterations;
  j["views"] = o.views;
  j["resolution"] = o.resolution;
  j["device"] = o.config.device;
  j["seed"] = o.config.seed;
  j["init"] = o.init;
  j["init_method"] = r.init_method;
  j["init_resolution"] = o.init_resolution > 0 ? o.init_resolution : o.resolution;
  j["variant"] = variant_name(o.variant);
  if (!failure.empty()) {
    for (const char* key : {"psnr", "ssim", "lpips"}) j[key] = nullptr;
  }
  if (o.variant != Variant::kVanilla) {
    j["gaps"] = o.gaps;
    j["generator"] = o.generator->name();
  }
  j["scene"] = o.scene_dir.string();
  j["config"] = o.config;
  for (const auto& v : r.per_view) {
    j["per_view"].push_back(
        {{"psnr", v.psnr}, {"ssim", v.ssim}, {"lpips", v.lpips ? nlohmann::json(*v.lpips) : nlohmann::json(nullptr)}});
  }
  return write_json(o.out_dir / "metrics.json", j);
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
      std::filesystem::create_directories(render_dir);
      GAPS_RETURN_IF_ERROR(
          write_png(render_dir / (std::filesystem::path(v.camera.name).stem().string() + ".png"), rgb.to(at::kCPU)));
    }
  }
  return out;
}

absl::Status run_init_only(const RunOptions& o, const std::function<void(const std::string&)>& log) {
  const at::Device device(o.config.device);
  SceneLoadOptions load;
  load.resolution = o.resolution;
  GAPS_ASSIGN_OR_RETURN(Scene scene, load_scene(o.scene_dir, load));
  GAPS_ASSIGN_OR_RETURN(Split split, benchmark_split(static_cast<int>(scene.cameras.size()), o.views));
  log(describe(scene, split));
  GAPS_ASSIGN_OR_RETURN(std::vector<TrainingView> train, load_views(scene, split.train, device));
  GAPS_ASSIGN_OR_RETURN(PointCloud points, initial_points(o, scene, train, log));
  std::filesystem::create_directories(o.out_dir);
  GAPS_RETURN_IF_ERROR(write_point_cloud_ply(points, o.out_dir / "points.ply"));
  std::vector<Camera> cameras;
  for (const auto& v : train) cameras.push_back(v.camera);
  GAPS_RETURN_IF_ERROR(write_init_as_colmap(o.out_dir / "sparse" / "0", cameras, points));
  log(absl::StrCat(points.xyz.size(0), " points written to ", (o.out_dir / "points.ply").string(), " and ",
                   (o.out_dir / "sparse" / "0").string()));
  return absl::OkStatus();
}

absl::StatusOr<RunResult> run_pipeline(const RunOptions& o, const ProgressCallback& on_progress,
                                       const std::function<void(const std::string&)>& log) {
  const at::Device device(o.config.device);
  if (device.is_cuda() && !at::hasCUDA())
    return absl::FailedPreconditionError("--device cuda requested but no CUDA device is available");
  std::optional<Lpips> lpips;
  if (!o.lpips_backbone.empty()) {
    GAPS_ASSIGN_OR_RETURN(lpips, Lpips::load(o.lpips_weights.string(), o.lpips_backbone.string()));
    lpips->to(device);
  }
  SceneLoadOptions load;
  load.resolution = o.resolution;
  GAPS_ASSIGN_OR_RETURN(Scene scene, load_scene(o.scene_dir, load));
  GAPS_ASSIGN_OR_RETURN(Split split, benchmark_split(static_cast<int>(scene.cameras.size()), o.views));
  RunResult result;
  result.summary = describe(scene, split);
  log(result.summary);
  GAPS_ASSIGN_OR_RETURN(std::vector<TrainingView> train, load_views(scene, split.train, device));
  GAPS_ASSIGN_OR_RETURN(std::vector<TrainingView> test, load_views(scene, split.test, device));
  GAPS_ASSIGN_OR_RETURN(PointCloud points, initial_points(o, scene, train, log, &result.init_method));
  log(absl::StrCat("initial points: ", points.xyz.size(0)));

  std::filesystem::create_directories(o.out_dir);
  const PeakMemoryMeter memory(device);
  const std::vector<TrainingView> references = train;
  Trainer trainer(gaussians_from_points(points, o.config.max_sh_degree).to(device), std::move(train), o.config);
  result.max_gaussians = trainer.config().max_gaussians;
  if (o.config.gaussians_per_variation > 0)
    log(absl::StrCat("automatic budget: ", result.max_gaussians, " Gaussians (", o.config.gaussians_per_variation,
                     " per unit of the training views' total variation)"));
  std::optional<TimedGenerator> generator;
  std::optional<GapsTraining> method;
  Trainer::StepFunction step = [&]() -> absl::StatusOr<at::Tensor> { return trainer.step(); };
  if (o.variant != Variant::kVanilla) {
    if (!o.generator)
      return absl::InvalidArgumentError(
          absl::StrCat("variant ", variant_name(o.variant), " needs a generator backend"));
    GapsConfig gaps = o.gaps;
    gaps.n_active = o.n_active > 0 ? o.n_active : (scene.cameras.size() > 100 ? kNActiveMip360 : kNActiveLlff);
    generator.emplace(o.generator);
    method.emplace(trainer, &*generator, references, gaps, o.variant, o.config.seed);
    method->set_inspection_dir(o.out_dir / "pseudo_views");
    if (o.on_phase || !o.checkpoint_dir.empty())
      method->set_phase_observer([&](const std::string& event, const nlohmann::json& entry) {
        if (event == "started" && !o.checkpoint_dir.empty()) {
          // The state before the phase: a resumed run repeats the phase, then goes on.
          if (const absl::Status saved = save_checkpoint(o.checkpoint_dir, trainer, &*method); !saved.ok())
            log(absl::StrCat("warning: checkpoint not written: ", saved.message()));
          else if (o.on_checkpoint)
            o.on_checkpoint(trainer.iteration());
        }
        if (o.on_phase) o.on_phase(event, entry);
      });
    step = [&] { return method->step(); };
    log(absl::StrCat("method: ", variant_name(o.variant), " with generator ", o.generator->name()));
  }
  const Lpips* lpips_model = lpips ? &*lpips : nullptr;
  if (!o.checkpoint_dir.empty()) {
    const absl::StatusOr<int> resumed = load_checkpoint(o.checkpoint_dir, trainer, method ? &*method : nullptr);
    if (resumed.ok())
      log(absl::StrCat("resumed from the checkpoint at iteration ", *resumed));
    else if (!absl::IsNotFound(resumed.status()))
      return resumed.status();
  }
  if (o.should_stop) {
    step = [&trainer, &o, inner = std::move(step)]() -> absl::StatusOr<at::Tensor> {
      if (o.should_stop()) return absl::CancelledError(absl::StrCat("stopped at iteration ", trainer.iteration()));
      return inner ? inner() : trainer.step();
    };
  }
  const auto start = std::chrono::steady_clock::now();
  const auto seconds_since = [](std::chrono::steady_clock::time_point t) {
    return std::chrono::duration<double>(std::chrono::steady_clock::now() - t).count();
  };
  double eval_seconds = 0.0;
  DivergenceGuard guard(kDivergenceCheckEvery, o.config.iterations);
  // Each iteration: the step, the divergence guard, and at the curve's iterations an evaluation whose time
  // is left out of the training time (the last iteration's is the final evaluation below).
  const Trainer::StepFunction monitored = [&]() -> absl::StatusOr<at::Tensor> {
    GAPS_ASSIGN_OR_RETURN(at::Tensor loss, step());
    const int it = trainer.iteration();
    GAPS_RETURN_IF_ERROR(guard.observe(it, loss, trainer.model()));
    if (o.eval_every <= 0 || it % o.eval_every != 0 || it >= o.config.iterations) return loss;
    (void)loss.item<double>();  // the queued training work belongs to the training time
    const auto eval_start = std::chrono::steady_clock::now();
    GAPS_ASSIGN_OR_RETURN(const std::vector<ImageMetrics> views,
                          evaluate_views(trainer.model(), test, o.config.background, lpips_model, {}));
    GAPS_ASSIGN_OR_RETURN(const ImageMetrics average, average_metrics(views));
    result.curve.push_back({it, std::chrono::duration<double>(eval_start - start).count() - eval_seconds, average,
                            trainer.model().size()});
    eval_seconds += seconds_since(eval_start);
    return loss;
  };
  const absl::Status trained = trainer.run(on_progress, 10, monitored);
  // A stopped run (cancelled, or its service shutting down) leaves its state for a later resume.
  if (absl::IsCancelled(trained) && !o.checkpoint_dir.empty()) {
    if (const absl::Status saved = save_checkpoint(o.checkpoint_dir, trainer, method ? &*method : nullptr); !saved.ok())
      log(absl::StrCat("warning: checkpoint not written: ", saved.message()));
    else if (o.on_checkpoint)
      o.on_checkpoint(trainer.iteration());
  }
  if (method) GAPS_RETURN_IF_ERROR(write_json(o.out_dir / "phases.json", method->phase_log()));
  result.train_seconds = seconds_since(start) - eval_seconds;
  result.num_gaussians = trainer.model().size();
  result.peak_memory = memory.read();
  if (generator) result.generator_seconds = generator->seconds();
  // Whatever happened, keep what was computed.
  GAPS_RETURN_IF_ERROR(save_gaussians_ply(trainer.model(), o.out_dir / "point_cloud.ply"));
  if (is_divergence(trained)) {
    log(std::string(trained.message()));
    GAPS_RETURN_IF_ERROR(write_metrics(o, result, "diverged", std::string(trained.message())));
    if (o.html_report) GAPS_RETURN_IF_ERROR(write_run_report(o.out_dir, test));
  }
  GAPS_RETURN_IF_ERROR(trained);

  GAPS_ASSIGN_OR_RETURN(result.per_view,
                        evaluate_views(trainer.model(), test, o.config.background, lpips_model,
                                       o.save_renders ? o.out_dir / "renders" : std::filesystem::path()));
  GAPS_ASSIGN_OR_RETURN(result.metrics, average_metrics(result.per_view));
  if (o.eval_every > 0)
    result.curve.push_back({o.config.iterations, result.train_seconds, result.metrics, result.num_gaussians});
  result.peak_memory = memory.read();
  GAPS_RETURN_IF_ERROR(write_metrics(o, result));
  if (o.html_report) GAPS_RETURN_IF_ERROR(write_run_report(o.out_dir, test));
  return result;
}

}  // namespace gaps

#include "gs_trainer/run/outputs.h"

#include <cmath>

#include <ATen/ATen.h>
#include <ATen/core/grad_mode.h>
#include <nlohmann/json.hpp>
#include "absl/strings/str_cat.h"
#include "common/image_io.h"
#include "common/io_util.h"
#include "common/status_macros.h"
#include "gs_trainer/model/render.h"
#include "gs_trainer/run/mvs_settings.h"
#include "gs_trainer/scene/cameras_json.h"
#include "gs_trainer/scene/run_files.h"

namespace gaps {

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

absl::Status write_metrics(const RunOptions& o, const RunResult& r, const std::string& failure,
                           const std::string& error) {
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

absl::Status write_run_cameras(const std::filesystem::path& path, const std::vector<TrainingView>& train,
                               const std::vector<TrainingView>& test) {
  std::vector<CameraRecord> cameras;
  for (const TrainingView& v : train) cameras.push_back({v.camera, "train"});
  for (const TrainingView& v : test) cameras.push_back({v.camera, "test"});
  return write_cameras_json(path, cameras);
}

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

std::vector<std::string> run_output_names() {
  return {
      "point_cloud.ply", "cameras.json",         "metrics.json",        "report.html",           "renders",
      "phases.json",     kPseudoViewsFolder,     "checkpoint",          "checkpoint.old",        "checkpoint.partial",
      "points.ply",      "sparse/0/cameras.txt", "sparse/0/images.txt", "sparse/0/points3D.txt", "dense"};
}

absl::Status make_folder(const std::filesystem::path& dir) {
  std::error_code ec;
  std::filesystem::create_directories(dir, ec);
  if (ec || !std::filesystem::is_directory(dir))
    return absl::PermissionDeniedError(
        absl::StrCat(dir.string(), ": cannot create the folder (", ec ? ec.message() : "not a folder", ")"));
  return absl::OkStatus();
}

absl::Status write_json(const std::filesystem::path& path, const nlohmann::json& j) {
  return write_file_bytes(path, j.dump(2) + "\n");
}

}  // namespace gaps

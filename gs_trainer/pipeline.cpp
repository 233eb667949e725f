#include "gs_trainer/pipeline.h"

#include <filesystem>
#include <optional>

#include <ATen/ATen.h>
#include "absl/strings/str_cat.h"
#include "common/device.h"
#include "common/error_kind.h"
#include "common/limits.h"
#include "common/ply.h"
#include "common/status_macros.h"
#include "gs_trainer/init/initializer.h"
#include "gs_trainer/report.h"
#include "gs_trainer/run/initial_model.h"
#include "gs_trainer/run/inputs.h"
#include "gs_trainer/run/training_run.h"
#include "gs_trainer/train/divergence.h"

namespace gaps {
namespace {

// metrics.json (see write_metrics) and, when asked for, report.html.
absl::Status write_outputs(const RunOptions& o, const RunResult& r, const std::vector<TrainingView>& test,
                           const std::string& failure = "", const std::string& error = "") {
  GAPS_RETURN_IF_ERROR(write_metrics(o, r, failure, error));
  if (o.html_report) GAPS_RETURN_IF_ERROR(write_run_report(o.out_dir, test));
  return absl::OkStatus();
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

absl::Status run_init_only(const RunOptions& o, const RunLog& log) {
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

absl::StatusOr<RunResult> run_pipeline(const RunOptions& o, const ProgressCallback& on_progress, const RunLog& log) {
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

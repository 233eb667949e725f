#pragma once
// What a run leaves: its result (RunResult) and metrics.json, cameras.json, the evaluation of a model on views
// with known images (the final one's renders written), and the names of everything it writes into out_dir.
#include <filesystem>
#include <optional>
#include <string>
#include <vector>

#include <nlohmann/json_fwd.hpp>
#include "absl/status/statusor.h"
#include "gs_trainer/eval/metrics.h"
#include "gs_trainer/model/gaussians.h"
#include "gs_trainer/run/initial_model.h"
#include "gs_trainer/run/options.h"
#include "gs_trainer/run/stats.h"
#include "gs_trainer/train/trainer.h"

namespace gaps {

class Lpips;

// What a run gives back, and metrics.json records.
struct RunResult {
  ImageMetrics metrics;
  std::vector<ImageMetrics> per_view;
  std::vector<std::string> per_view_images;  // the test images of per_view, in the same order
  int64_t num_gaussians = 0;
  int64_t max_gaussians = 0;      // the budget the run trained under (resolved when automatic); 0 = none
  double train_seconds = 0.0;     // without the evaluations of the curve and the checkpoints
  std::string summary;            // what was loaded
  std::vector<CurvePoint> curve;  // ends with the final evaluation when eval_every > 0
  PeakMemory peak_memory;
  std::optional<double> generator_seconds;  // method variants only
  InitRecord init;
  // The method's diffusion phases: how many ran and how many were skipped because no generator answered.
  // A run with skipped phases trained on fewer pseudo-views than it was asked to: metrics.json says
  // "degraded": true, and the services mark the job DEGRADED.
  int phases = 0;
  int phases_skipped = 0;
  bool degraded() const { return phases_skipped > 0; }
  // The options the run used, automatic values resolved (the Gaussian budget in config.max_gaussians, the
  // pseudo-views per phase in gaps.n_active): what metrics.json records.
  TrainConfig config;
  GapsConfig gaps;
};

// metrics.json's record of what ran: the run-level options and, from `result`, the effective TrainConfig and
// (for the method's variants) GapsConfig and generator.
nlohmann::json run_configuration_json(const RunOptions& options, const RunResult& result);

// `failure` empty: metrics.json of a finished run; otherwise the run's status ("diverged") and error, without
// final metrics.
absl::Status write_metrics(const RunOptions& o, const RunResult& r, const std::string& failure = "",
                           const std::string& error = "");

// cameras.json (gs_trainer/scene/cameras_json.h): the training views, then the test views.
absl::Status write_run_cameras(const std::filesystem::path& path, const std::vector<TrainingView>& train,
                               const std::vector<TrainingView>& test);

// Evaluates a model on cameras with known images; writes renders to `render_dir` when not empty.
absl::StatusOr<std::vector<ImageMetrics>> evaluate_views(const GaussianModel& model,
                                                         const std::vector<TrainingView>& views, double background,
                                                         const Lpips* lpips, const std::filesystem::path& render_dir);

// The run's final evaluation on the test views: per view (renders written when asked for), averaged, and as
// the curve's last point.
absl::Status evaluate_final(const RunOptions& o, const GaussianModel& model, const std::vector<TrainingView>& test,
                            const Lpips* lpips, RunResult* result);

// What run_pipeline and run_init_only write into out_dir (files and folders, checkpoints included), so that
// a command reusing the folder can remove an earlier run's results first.
std::vector<std::string> run_output_names();

// `dir` and the folders above it, as a status instead of the exception of create_directories.
absl::Status make_folder(const std::filesystem::path& dir);

// `j` as indented text, written whole.
absl::Status write_json(const std::filesystem::path& path, const nlohmann::json& j);

}  // namespace gaps

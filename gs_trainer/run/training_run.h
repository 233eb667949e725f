#pragma once
// The training part of a run: the trainer, the method on top of it, the evaluation curve and the checkpoints.
#include <chrono>
#include <optional>
#include <set>
#include <string>
#include <vector>

#include <ATen/ATen.h>
#include <nlohmann/json_fwd.hpp>
#include "absl/status/statusor.h"
#include "gs_trainer/gaps/training.h"
#include "gs_trainer/model/gaussians.h"
#include "gs_trainer/run/options.h"
#include "gs_trainer/run/stats.h"
#include "gs_trainer/train/divergence.h"
#include "gs_trainer/train/trainer.h"

namespace gaps {

class Lpips;
struct RunResult;

// The trainer and, for the paper's variants, the method driving it, from the initial points to the end of
// training. The method refers to the trainer, hence neither copied nor moved.
class TrainingRun {
 public:
  TrainingRun(const RunOptions& o, const RunLog& log, const GaussianModel& initial, std::vector<TrainingView> train,
              const at::Device& device);
  TrainingRun(const TrainingRun&) = delete;
  TrainingRun& operator=(const TrainingRun&) = delete;

  const Trainer& trainer() const { return trainer_; }
  std::optional<double> generator_seconds() const;
  // Wall-clock training time, without the curve's evaluations and the checkpoints, including a resumed run's
  // earlier part.
  double train_seconds() const { return seconds_since_start(std::chrono::steady_clock::now()); }
  // The evaluations so far (a resumed run's earlier ones first).
  const std::vector<CurvePoint>& curve() const { return curve_; }

  // The method's options as used: n_active resolved from the training views' layout when 0.
  GapsConfig effective_gaps() const;

  // The paper's method, with `gaps` (effective_gaps()), on top of the trainer; nothing for the vanilla variant.
  absl::Status attach_method(const GapsConfig& gaps);

  // Goes on from the checkpoint in o.checkpoint_dir, if there is one, with the curve and training time
  // it kept.
  absl::Status resume();

  // Trains to the last iteration unless stopped (should_stop) or diverged; every o.eval_every iterations
  // the test views are evaluated into the curve.
  absl::Status train(const ProgressCallback& on_progress, const std::vector<TrainingView>& test, const Lpips* lpips);

  // After train(): a stopped run (cancelled, or its service shutting down) leaves its state for a later
  // resume; the method's phases go to phases.json.
  absl::Status keep_state(const absl::Status& trained);

  // Phases run and skipped so far, into *result.
  void count_phases(RunResult* result) const;

 private:
  GapsTraining* method() { return method_ ? &*method_ : nullptr; }

  // What the generator could not honour of the job's controls, in the run log the first time it comes up
  // (phases.json keeps every phase's notes).
  void log_generator_notes(const nlohmann::json& entry);

  // Every checkpoint_every iterations, or checkpoint_every_seconds after the last save (or the start).
  bool checkpoint_due(int it) const;

  // The training state to o.checkpoint_dir (when set); a failure costs the checkpoint only, with a warning.
  void save_checkpoint_and_tell();

  double seconds_since_start(std::chrono::steady_clock::time_point t) const;

  // One iteration of the method (or of the trainer alone), unless should_stop says otherwise.
  absl::StatusOr<at::Tensor> next_step();

  // The step, the divergence guard, at the curve's iterations an evaluation whose time is left out of the
  // training time (the last iteration's is the run's final evaluation), and the periodic checkpoint.
  absl::StatusOr<at::Tensor> monitored_step(const std::vector<TrainingView>& test, const Lpips* lpips);

  absl::Status evaluate_for_curve(int it, const at::Tensor& loss, const std::vector<TrainingView>& test,
                                  const Lpips* lpips);

  const RunOptions& o_;
  const RunLog& log_;
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

}  // namespace gaps

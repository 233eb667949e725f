#include "gs_trainer/run/training_run.h"

#include <nlohmann/json.hpp>
#include "absl/strings/str_cat.h"
#include "common/status_macros.h"
#include "gs_trainer/init/initializer.h"
#include "gs_trainer/run/checkpoint.h"
#include "gs_trainer/run/inputs.h"
#include "gs_trainer/run/outputs.h"
#include "gs_trainer/scene/run_files.h"

namespace gaps {
namespace {

// Loss and parameters are checked for finiteness this often (one device synchronisation each time).
constexpr int kDivergenceCheckEvery = 10;

}  // namespace

TrainingRun::TrainingRun(const RunOptions& o, const RunLog& log, const GaussianModel& initial,
                         std::vector<TrainingView> train, const at::Device& device)
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

std::optional<double> TrainingRun::generator_seconds() const {
  return generator_ ? std::optional<double>(generator_->seconds()) : std::nullopt;
}

GapsConfig TrainingRun::effective_gaps() const {
  GapsConfig gaps = o_.gaps;
  gaps.n_active = n_active_for(o_.gaps, views_surround_scene(cameras_of(references_)));
  return gaps;
}

absl::Status TrainingRun::attach_method(const GapsConfig& gaps) {
  if (o_.variant == Variant::kVanilla) return absl::OkStatus();
  if (!o_.generator)
    return absl::InvalidArgumentError(absl::StrCat("variant ", variant_name(o_.variant), " needs a generator backend"));
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

absl::Status TrainingRun::resume() {
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

absl::Status TrainingRun::train(const ProgressCallback& on_progress, const std::vector<TrainingView>& test,
                                const Lpips* lpips) {
  start_ = last_save_ = std::chrono::steady_clock::now();
  if (o_.on_training_started) o_.on_training_started();
  return trainer_.run(on_progress, 10, [&] { return monitored_step(test, lpips); });
}

absl::Status TrainingRun::keep_state(const absl::Status& trained) {
  if (absl::IsCancelled(trained)) save_checkpoint_and_tell();
  if (!method_) return absl::OkStatus();
  // A phase started near the end (async_iterations) is judged and logged, though nothing trains on it any more.
  const absl::Status joined = method_->finish_pending_phase();
  const absl::Status inspected = method_->finish_inspection();
  GAPS_RETURN_IF_ERROR(write_json(o_.out_dir / "phases.json", method_->phase_log()));
  GAPS_RETURN_IF_ERROR(joined);
  return inspected;
}

void TrainingRun::count_phases(RunResult* result) const {
  if (!method_) return;
  for (const auto& entry : method_->phase_log()) {
    ++result->phases;
    if (entry.value("skipped", false)) ++result->phases_skipped;
  }
}

void TrainingRun::log_generator_notes(const nlohmann::json& entry) {
  if (!entry.contains("generator_notes")) return;
  for (const auto& note : entry["generator_notes"]) {
    if (logged_notes_.insert(note.get<std::string>()).second)
      log_(absl::StrCat("generator note (phase ", entry.value("phase", -1), "): ", note.get<std::string>()));
  }
}

bool TrainingRun::checkpoint_due(int it) const {
  // A checkpoint holds no phase in flight: the save waits until its views are admitted, where the run would have
  // admitted them anyway (joining early would make the run depend on when it was saved).
  if (method_ && method_->phase_pending()) return false;
  if (o_.checkpoint_every > 0 && it % o_.checkpoint_every == 0) return true;
  return o_.checkpoint_every_seconds > 0 &&
         std::chrono::duration<double>(std::chrono::steady_clock::now() - last_save_).count() >=
             o_.checkpoint_every_seconds;
}

void TrainingRun::save_checkpoint_and_tell() {
  if (o_.checkpoint_dir.empty()) return;
  // A resumed run does not redo the phases before its checkpoint, so their images must be on disk first; a
  // failed write is the next phase's (or the run end's) error.
  if (method_) {
    // Only a stop reaches here with a phase in flight: its views are admitted now rather than lost.
    if (const absl::Status joined = method_->finish_pending_phase(); !joined.ok())
      log_(absl::StrCat("warning: the phase in flight failed: ", joined.message()));
    (void)method_->finish_inspection();
  }
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

double TrainingRun::seconds_since_start(std::chrono::steady_clock::time_point t) const {
  return seconds_before_ + std::chrono::duration<double>(t - start_).count() - excluded_seconds_;
}

absl::StatusOr<at::Tensor> TrainingRun::next_step() {
  if (o_.should_stop && o_.should_stop())
    return absl::CancelledError(absl::StrCat("stopped at iteration ", trainer_.iteration()));
  if (method_) return method_->step();
  return trainer_.step();
}

absl::StatusOr<at::Tensor> TrainingRun::monitored_step(const std::vector<TrainingView>& test, const Lpips* lpips) {
  GAPS_ASSIGN_OR_RETURN(at::Tensor loss, next_step());
  const int it = trainer_.iteration();
  GAPS_RETURN_IF_ERROR(guard_.observe(it, loss, trainer_.model()));
  if (it < o_.config.iterations) {
    GAPS_RETURN_IF_ERROR(evaluate_for_curve(it, loss, test, lpips));
    if (checkpoint_due(it)) save_checkpoint_and_tell();
  }
  return loss;
}

absl::Status TrainingRun::evaluate_for_curve(int it, const at::Tensor& loss, const std::vector<TrainingView>& test,
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

}  // namespace gaps

#pragma once
// The alternating optimisation of the paper (sec. 3.2): GT-only warmup, then a diffusion phase every
// phase_interval iterations (GAPS selection, generation, admission), and between phases iterations that
// train on an admitted pseudo-view with probability p_pseudo, all under density-adaptive DropGaussian.
// Variants for the ablation: vanilla, full, no-gaps (the paper's static baseline: the midpoints of 8
// training pairs, pose.h static_midpoints, generated once in the first phase, all admitted, trained with
// the full method's uncertainty weights), no-dropgaussian. A generator answering UNAVAILABLE (e.g. no remote
// worker reachable) skips the phase: it is logged with "skipped" and training goes on with the pseudo-views
// admitted so far.
#include <chrono>
#include <filesystem>
#include <functional>
#include <future>
#include <map>
#include <optional>
#include <random>
#include <set>
#include <string>
#include <vector>

#include <ATen/Tensor.h>
#include <ATen/core/Generator.h>
#include <nlohmann/json.hpp>
#include "absl/status/statusor.h"
#include "gs_trainer/gaps/config.h"
#include "gs_trainer/gaps/generator.h"
#include "gs_trainer/gaps/pose.h"
#include "gs_trainer/gaps/scores.h"
#include "gs_trainer/model/render.h"
#include "gs_trainer/train/trainer.h"

namespace gaps {

enum class Variant { kVanilla, kFull, kNoGaps, kNoDropGaussian };
absl::StatusOr<Variant> parse_variant(const std::string& name);
std::string variant_name(Variant v);

// The generation request of one selected pose: the full-fidelity render there (moved to the CPU), its coverage
// and the coverage-adaptive controls (eq. adaptive_strength, adaptive_cn), the references nearest first, the
// seed, the two-stage settings and λ_ip.
GenerationRequest generation_request(const Camera& pose, const RenderOutput& render,
                                     std::vector<ReferenceView> references, const GapsConfig& c, uint64_t seed);

// The training views as a generator's references: each photograph with the model's depth and alpha at its pose
// (for warping), on the CPU.
std::vector<ReferenceView> reference_views(const GaussianModel& model, const std::vector<TrainingView>& views);
// `references` nearest to `pose` first (pose_distance with `rotation_weight`), equal distances in their order.
std::vector<ReferenceView> nearest_first(const Camera& pose, std::vector<ReferenceView> references,
                                         double rotation_weight);

class GapsTraining {
 public:
  // `gt_views` are the trainer's training views (the references for generation).
  GapsTraining(Trainer& trainer, Generator* generator, std::vector<TrainingView> gt_views, GapsConfig config,
               Variant variant, uint64_t seed);

  // One iteration: a diffusion phase first when one is due (with async_iterations > 0 the phase only starts its
  // generation, and the pseudo-views are judged and admitted async_iterations later, or before the next phase),
  // then a pseudo or GT step.
  absl::StatusOr<at::Tensor> step();
  // Waits for a phase whose pseudo-views are still being generated, then judges and admits them and logs the
  // phase; a no-op when none is. The run calls it before saving a checkpoint and at its end.
  absl::Status finish_pending_phase();
  bool phase_pending() const { return pending_.has_value(); }
  // Per phase: candidates and scores, the selection, admissions with reasons, tier, beta, drop ratio, and
  // "generator_notes" when the generator could not honour all of the job's controls (Generator::notes()).
  const nlohmann::json& phase_log() const { return log_; }
  // The active set: the admitted pseudo-views trained on now, by candidate id (active_set.h).
  const std::map<int, PseudoView>& active() const { return active_; }
  // When set, every phase's generated images are written there as phase_PP/cand_III_{admitted,rejected}.png, in
  // the background while training goes on (a phase first waits for the previous phase's).
  void set_inspection_dir(const std::filesystem::path& dir) { inspection_dir_ = dir; }
  // Waits until the images of every phase so far are written; the first write that failed, if one did (it
  // fails the next phase too). Called before a checkpoint and at the end of the run.
  absl::Status finish_inspection();
  // Called as phases start ("started", with phase and iteration), end ("finished", with the phase's log
  // entry) or are skipped ("skipped", with a "skip_reason").
  using PhaseObserver = std::function<void(const std::string& event, const nlohmann::json& entry)>;
  void set_phase_observer(PhaseObserver observer) { phase_observer_ = std::move(observer); }

 private:
  friend struct CheckpointAccess;  // gs_trainer/run/checkpoint.cpp saves and restores this state
  // A phase whose generation was asked for: what its admission needs once the images are there.
  struct PendingPhase {
    nlohmann::json entry;
    std::vector<Candidate> chosen;
    std::vector<RenderOutput> renders;
    std::vector<GenerationRequest> requests;
    bool gate = true;
    int launched_before = 0;  // the iteration the phase ran before
    int join_before = 0;      // the iteration before which its views are admitted
    std::chrono::steady_clock::time_point launched;
    std::future<absl::StatusOr<std::vector<at::Tensor>>> images;  // async only
  };
  // Adapts the generator at the run's first step rather than at the first phase, so that a generator that
  // adapts in the background (the worker pool: sdxl's LoRA training) overlaps the iterations before it.
  void adapt_early(int next);
  absl::Status run_phase(int phase);
  absl::Status run_phase_generation(int phase, nlohmann::json& entry);
  // Renders the chosen poses and makes their requests; then generates and admits at once, or (async_iterations
  // > 0) starts the generation on a thread of its own and leaves the rest in pending_.
  absl::Status generate_and_admit(const std::vector<Candidate>& chosen, bool gate, nlohmann::json& entry);
  absl::Status admit_generated(PendingPhase& phase, std::vector<at::Tensor> images);
  // Logs a phase that ended (skipped when the generator was unavailable) and tells the observer.
  absl::Status close_phase(nlohmann::json& entry, const absl::Status& generated);
  // Applies this phase's admissions to the active set and records the change in the phase's entry.
  void update_active_set(std::map<int, PseudoView> admitted, const std::vector<int>& admitted_order,
                         const std::vector<int>& rejected, bool gate, nlohmann::json& entry);
  // Where a generated view is saved for inspection (its phase's folder made); empty without an inspection dir.
  std::filesystem::path inspection_path(int phase, int id, bool admitted) const;
  at::Tensor drop_scale();
  std::vector<Camera> supervised_cameras() const;

  Trainer& trainer_;
  Generator* generator_;
  std::vector<TrainingView> gt_views_;
  std::vector<Camera> gt_cameras_;
  GapsConfig config_;
  Variant variant_;
  std::mt19937_64 rng_;
  uint64_t seed_;
  // DropGaussian's masks come from a generator of the run's own (seeded from `seed_`, on the model's device)
  // so that a run of the method is reproducible whatever else draws from ATen's default generator.
  at::Generator drop_rng_;
  int tier_ = 0;
  bool adapted_ = false;
  bool early_adaptation_tried_ = false;
  nlohmann::json early_adaptation_;         // iteration, seconds and notes of that call, for the first phase's entry
  std::map<int, PseudoView> active_;        // candidate id -> its admitted view trained on now
  std::map<int, int> active_phase_;         // candidate id -> the phase its active view was generated in
  std::set<int> ever_admitted_;             // every candidate admitted at least once (forced exploration)
  UncertaintyHistory uncertainty_history_;  // every generation's variance, admitted or not (C_hist)
  std::filesystem::path inspection_dir_;
  std::future<absl::Status> inspection_written_;  // the last phase's images; its destructor waits for them
  absl::Status inspection_error_;
  std::vector<ReferenceView> gt_renders_;  // GT views with the model's renders, per phase
  std::optional<PendingPhase> pending_;    // a phase whose pseudo-views are being generated
  nlohmann::json log_ = nlohmann::json::array();
  PhaseObserver phase_observer_;
};

}  // namespace gaps

#include "gs_trainer/gaps/training.h"

#include <algorithm>
#include <chrono>
#include <numeric>

#include <ATen/ATen.h>
#include <ATen/core/grad_mode.h>
#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "common/image_io.h"
#include "common/status_macros.h"
#include "common/stopwatch.h"
#include "gs_trainer/gaps/active_set.h"
#include "gs_trainer/gaps/admission.h"
#include "gs_trainer/gaps/candidate_renders.h"
#include "gs_trainer/gaps/scores.h"
#include "gs_trainer/model/render.h"
#include "gs_trainer/scene/cameras_json.h"
#include "gs_trainer/scene/run_files.h"

namespace gaps {

absl::StatusOr<Variant> parse_variant(const std::string& name) {
  if (name == "vanilla") return Variant::kVanilla;
  if (name == "full") return Variant::kFull;
  if (name == "no-gaps") return Variant::kNoGaps;
  if (name == "no-dropgaussian") return Variant::kNoDropGaussian;
  return absl::InvalidArgumentError(
      absl::StrCat("unknown variant '", name, "' (vanilla, full, no-gaps, no-dropgaussian)"));
}

std::string variant_name(Variant v) {
  switch (v) {
    case Variant::kVanilla:
      return "vanilla";
    case Variant::kFull:
      return "full";
    case Variant::kNoGaps:
      return "no-gaps";
    case Variant::kNoDropGaussian:
      return "no-dropgaussian";
  }
  return "?";
}

GenerationRequest generation_request(const Camera& pose, const RenderOutput& render,
                                     std::vector<ReferenceView> references, const GapsConfig& c, uint64_t seed) {
  GenerationRequest q;
  q.camera = pose;
  q.render_rgb = render.rgb.clamp(0, 1).cpu();
  q.render_depth = render.depth.cpu();
  q.render_alpha = render.alpha.cpu();
  q.coverage = coverage_fraction(render.alpha, c.coverage_alpha_threshold);
  q.strength = adaptive_strength(q.coverage, c);
  q.control_scale = adaptive_control_scale(q.coverage, c);
  q.references = std::move(references);
  q.seed = seed;
  q.inpaint = inpaint_settings(c);
  q.ip_adapter_scale = c.ip_adapter_scale;
  return q;
}

std::vector<ReferenceView> reference_views(const GaussianModel& model, const std::vector<TrainingView>& views) {
  std::vector<Camera> cameras;
  for (const TrainingView& v : views) cameras.push_back(v.camera);
  const std::vector<RenderOutput> renders = render_views(model, cameras);  // one stacked pass per image size
  std::vector<ReferenceView> out;
  for (size_t k = 0; k < views.size(); ++k)
    out.push_back({views[k].camera, views[k].image.cpu(), renders[k].depth.cpu(), renders[k].alpha.cpu()});
  return out;
}

std::vector<ReferenceView> nearest_first(const Camera& pose, std::vector<ReferenceView> references,
                                         double rotation_weight) {
  std::vector<double> distance;
  for (const ReferenceView& r : references) distance.push_back(pose_distance(pose, r.camera, rotation_weight));
  std::vector<size_t> order(references.size());
  std::iota(order.begin(), order.end(), size_t{0});
  std::stable_sort(order.begin(), order.end(), [&](size_t a, size_t b) { return distance[a] < distance[b]; });
  std::vector<ReferenceView> out;
  for (size_t i : order) out.push_back(std::move(references[i]));
  return out;
}

GapsTraining::GapsTraining(Trainer& trainer, Generator* generator, std::vector<TrainingView> gt_views,
                           GapsConfig config, Variant variant, uint64_t seed)
    : trainer_(trainer),
      generator_(generator),
      gt_views_(std::move(gt_views)),
      config_(std::move(config)),
      variant_(variant),
      rng_(seed ^ 0x9e3779b97f4a7c15ULL),
      seed_(seed) {
  for (const auto& v : gt_views_) gt_cameras_.push_back(v.camera);
  TORCH_CHECK(variant_ == Variant::kVanilla || generator_ != nullptr, "variant ", variant_name(variant_),
              " needs a generator");
}

at::Tensor GapsTraining::drop_scale() {
  if (variant_ == Variant::kVanilla || variant_ == Variant::kNoDropGaussian) return {};
  const auto& model = trainer_.model();
  const double r = drop_ratio(trainer_.iteration() + 1, trainer_.config().iterations, model.size(), config_,
                              trainer_.config().max_gaussians);
  if (r <= 0) return {};
  if (!drop_rng_.defined() || drop_rng_.device() != model.means.device()) {
    drop_rng_ = at::globalContext().defaultGenerator(model.means.device()).clone();
    drop_rng_.set_current_seed(seed_ ^ 0xd1b54a32d192ed03ULL);
  }
  return drop_gaussian_scale(model.size(), r, drop_rng_, model.means.options());
}

void GapsTraining::adapt_early(int next) {
  early_adaptation_tried_ = true;
  const int total = trainer_.config().iterations, phases = num_diffusion_phases(total, config_);
  // Only when a phase is still to come: a run too short for one adapts nothing (a LoRA costs minutes on a CPU).
  if (phases == 0 || next > config_.warmup_iterations + (phases - 1) * config_.phase_interval) return;
  auto start = std::chrono::steady_clock::now();
  const absl::Status adapted =
      generator_->adapt(reference_views(trainer_.model(), gt_views_), scene_adaptation(config_));
  // A failure is not the run's: the first phase adapts again and reports it there, as without this.
  if (!adapted.ok()) return;
  adapted_ = true;
  early_adaptation_ = nlohmann::json::object();
  early_adaptation_["before_iteration"] = next;
  early_adaptation_["seconds"] = lap_seconds(&start);
  for (const std::string& note : generator_->notes()) early_adaptation_["notes"].push_back(note);
}

absl::StatusOr<at::Tensor> GapsTraining::step() {
  const int next = trainer_.iteration() + 1;
  if (variant_ != Variant::kVanilla) {
    if (!adapted_ && !early_adaptation_tried_) adapt_early(next);
    const int phase = diffusion_phase_at(next, trainer_.config().iterations, config_);
    if (pending_ && (phase >= 0 || next >= pending_->join_before)) GAPS_RETURN_IF_ERROR(finish_pending_phase());
    if (phase >= 0) GAPS_RETURN_IF_ERROR(run_phase(phase));
  }
  const at::Tensor scale = drop_scale();
  std::uniform_real_distribution<double> u(0.0, 1.0);
  if (!active_.empty() && next > config_.warmup_iterations && u(rng_) < config_.pseudo_probability) {
    std::uniform_int_distribution<size_t> pick(0, active_.size() - 1);
    auto it = active_.begin();
    std::advance(it, pick(rng_));
    return trainer_.step_pseudo(it->second, scale);
  }
  return trainer_.step(scale);
}

std::vector<Camera> GapsTraining::supervised_cameras() const {
  std::vector<Camera> cams = gt_cameras_;
  for (const auto& [id, v] : active_) cams.push_back(v.camera);
  return cams;
}

absl::Status GapsTraining::run_phase(int phase) {
  at::AutoGradMode no_grad(false);
  const GaussianModel& model = trainer_.model();
  const int t = trainer_.iteration(), T = trainer_.config().iterations;
  nlohmann::json entry = {{"phase", phase},
                          {"iteration", t},
                          {"tier", tier_},
                          {"gaussians", model.size()},
                          {"drop_ratio", drop_ratio(t, T, model.size(), config_, trainer_.config().max_gaussians)},
                          {"drop_threshold", drop_threshold(config_, trainer_.config().max_gaussians)},
                          {"beta", annealed_beta(t, T, config_)}};
  if (variant_ == Variant::kNoGaps && phase > 0) return absl::OkStatus();  // generated once, never refreshed
  if (phase_observer_) phase_observer_("started", entry);
  const absl::Status generated = run_phase_generation(phase, entry);
  if (generated.ok() && pending_) return absl::OkStatus();  // closed when its views are admitted
  return close_phase(entry, generated);
}

absl::Status GapsTraining::close_phase(nlohmann::json& entry, const absl::Status& generated) {
  if (generated.code() != absl::StatusCode::kUnavailable) GAPS_RETURN_IF_ERROR(generated);
  if (!generated.ok()) {
    entry["skipped"] = true;
    entry["skip_reason"] = std::string(generated.message());
  }
  log_.push_back(entry);
  if (phase_observer_) phase_observer_(generated.ok() ? "finished" : "skipped", entry);
  return absl::OkStatus();
}

absl::Status GapsTraining::finish_pending_phase() {
  if (!pending_) return absl::OkStatus();
  at::AutoGradMode no_grad(false);
  PendingPhase phase = std::move(*pending_);
  pending_.reset();
  const auto wait_start = std::chrono::steady_clock::now();
  absl::StatusOr<std::vector<at::Tensor>> images = phase.images.get();
  const auto now = std::chrono::steady_clock::now();
  phase.entry["async"] = {{"launched_before", phase.launched_before},
                          {"joined_before", trainer_.iteration() + 1},
                          {"generation_seconds", std::chrono::duration<double>(now - phase.launched).count()},
                          {"waited_seconds", std::chrono::duration<double>(now - wait_start).count()}};
  phase.entry["seconds"]["generation"] = std::chrono::duration<double>(now - wait_start).count();
  const absl::Status admitted =
      images.ok() ? admit_generated(phase, *std::move(images)) : absl::Status(images.status());
  return close_phase(phase.entry, admitted);
}

namespace {

// Adds the seconds since *start to entry["seconds"][section] and restarts the clock: the phase's time
// breakdown (renders and scores reach the host before the next section starts, so GPU work is included).
void lap(nlohmann::json& entry, const char* section, std::chrono::steady_clock::time_point* start) {
  nlohmann::json& seconds = entry["seconds"];
  if (!seconds.is_object()) seconds = nlohmann::json::object();
  seconds[section] = seconds.value(section, 0.0) + lap_seconds(start);
}

// What the generator's last call could not honour of the job's controls, kept with the phase.
void record_generator_notes(const Generator& generator, nlohmann::json& entry) {
  for (const std::string& note : generator.notes()) entry["generator_notes"].push_back(note);
}

}  // namespace

absl::Status GapsTraining::run_phase_generation(int phase, nlohmann::json& entry) {
  const GaussianModel& model = trainer_.model();
  const int t = trainer_.iteration(), T = trainer_.config().iterations;

  auto clock = std::chrono::steady_clock::now();
  // The model's current renders at the GT poses: the references carry them (depth for warping).
  gt_renders_ = reference_views(model, gt_views_);
  lap(entry, "references", &clock);
  if (!adapted_) {
    GAPS_RETURN_IF_ERROR(generator_->adapt(gt_renders_, scene_adaptation(config_)));
    lap(entry, "adaptation", &clock);
    record_generator_notes(*generator_, entry);
    adapted_ = true;
  } else if (!early_adaptation_.is_null()) {
    // The adaptation started at the run's first step belongs to this, the first phase after it.
    entry["early_adaptation"] = std::move(early_adaptation_);
    for (const auto& note : entry["early_adaptation"].value("notes", nlohmann::json::array()))
      entry["generator_notes"].push_back(note);
    early_adaptation_ = nullptr;
  }

  std::vector<Candidate> chosen;
  if (variant_ == Variant::kNoGaps) {
    chosen = static_midpoints(gt_cameras_, config_);
  } else {
    std::vector<Candidate> pool = build_candidate_pool(gt_cameras_, config_, tier_);
    const std::vector<Camera> supervised = supervised_cameras();
    std::vector<Camera> cameras;
    for (const Candidate& c : pool) cameras.push_back(c.camera);
    const at::Tensor statistics = candidate_statistics(model, cameras, config_);
    const double* rows = statistics.data_ptr<double>();
    std::vector<double> scores;
    int never_generated = 0, never_admitted = 0;
    for (size_t k = 0; k < pool.size(); ++k) {
      Candidate& c = pool[k];
      c.admitted_before = ever_admitted_.count(c.id) > 0;
      never_generated += uncertainty_history_.count(c.id) == 0;
      never_admitted += !c.admitted_before;
      const auto m = measurements_from(rows + 4 * k, min_pose_distance(c.camera, supervised),
                                       min_pose_distance(c.camera, gt_cameras_),
                                       mean_uncertainty_variance(uncertainty_history_, c.id));
      const ScoreTerms s = score_candidate(m, t, T, config_);
      scores.push_back(s.score);
      entry["candidates"].push_back({{"id", c.id},
                                     {"pair", {c.i, c.j}},
                                     {"alpha", c.alpha},
                                     {"i_recon", s.i_recon},
                                     {"c_model", s.c_model},
                                     {"c_gen", s.c_gen},
                                     {"score", s.score}});
    }
    entry["pool"] = {{"size", pool.size()}, {"never_generated", never_generated}, {"never_admitted", never_admitted}};
    for (int k : select_for_phase(pool, scores, phase, config_)) chosen.push_back(pool[k]);
    lap(entry, "scoring", &clock);
  }
  return generate_and_admit(chosen, variant_ != Variant::kNoGaps, entry);
}

std::filesystem::path GapsTraining::inspection_path(int phase, int id, bool admitted) const {
  if (inspection_dir_.empty()) return {};
  const std::filesystem::path path = inspection_dir_ / pseudo_view_file(phase, id, admitted);
  std::filesystem::create_directories(path.parent_path());
  return path;
}

absl::Status GapsTraining::generate_and_admit(const std::vector<Candidate>& chosen, bool gate, nlohmann::json& entry) {
  const GaussianModel& model = trainer_.model();
  auto clock = std::chrono::steady_clock::now();
  PendingPhase phase;
  phase.chosen = chosen;
  phase.gate = gate;
  std::vector<Camera> poses;
  for (const auto& c : chosen) poses.push_back(c.camera);
  phase.renders = render_views(model, poses);  // one stacked pass per image size
  for (size_t k = 0; k < chosen.size(); ++k)
    phase.requests.push_back(generation_request(
        chosen[k].camera, phase.renders[k], nearest_first(chosen[k].camera, gt_renders_, config_.pose_rotation_weight),
        config_, rng_()));
  lap(entry, "renders", &clock);
  phase.launched_before = trainer_.iteration() + 1;
  if (config_.async_iterations > 0) {
    phase.entry = entry;
    phase.join_before = phase.launched_before + config_.async_iterations;
    phase.launched = std::chrono::steady_clock::now();
    // The requests are CPU tensors (generation_request); the generator is not used elsewhere until the join.
    phase.images = std::async(std::launch::async, [generator = generator_, requests = phase.requests] {
      return generator->generate(requests);
    });
    pending_ = std::move(phase);
    return absl::OkStatus();
  }
  GAPS_ASSIGN_OR_RETURN(std::vector<at::Tensor> images, generator_->generate(phase.requests));
  lap(entry, "generation", &clock);
  phase.entry = std::move(entry);
  const absl::Status admitted = admit_generated(phase, std::move(images));
  entry = std::move(phase.entry);
  return admitted;
}

absl::Status GapsTraining::admit_generated(PendingPhase& phase, std::vector<at::Tensor> images) {
  const GaussianModel& model = trainer_.model();
  auto clock = std::chrono::steady_clock::now();
  nlohmann::json& entry = phase.entry;
  const std::vector<Candidate>& chosen = phase.chosen;
  const std::vector<RenderOutput>& renders = phase.renders;
  const std::vector<GenerationRequest>& requests = phase.requests;
  const bool gate = phase.gate;
  record_generator_notes(*generator_, entry);
  for (const auto& [stage, seconds] : generator_->stage_seconds()) entry["generator_stages"][stage] = seconds;
  for (const auto& [name, count] : generator_->counters()) entry["generator_counters"][name] = count;
  if (images.size() != requests.size())
    return absl::InternalError(absl::StrCat("generator ", generator_->name(), " returned ", images.size(),
                                            " images for ", requests.size(), " requests"));
  std::vector<double> admitted_variances;
  std::vector<std::pair<std::filesystem::path, at::Tensor>> for_inspection;
  std::map<int, PseudoView> admitted;
  std::vector<int> admitted_order, rejected;
  const auto device = model.means.device();
  for (size_t k = 0; k < chosen.size(); ++k) {
    const at::Tensor image = images[k].to(device);
    const at::Tensor rendered = renders[k].rgb.clamp(0, 1), alpha = renders[k].alpha;
    const AdmissionDecision d = admit_pseudo_view(image, rendered, alpha, config_, requests[k].strength);
    const bool admit = !gate || d.admitted;
    const double variance = uncertainty_variance(d.uncertainty);
    uncertainty_history_[chosen[k].id].push_back(variance);
    nlohmann::json row = {{"id", chosen[k].id},
                          {"pair", {chosen[k].i, chosen[k].j}},
                          {"alpha", chosen[k].alpha},
                          {"coverage", requests[k].coverage},
                          {"strength", requests[k].strength},
                          {"residual", d.mean_residual},
                          {"uncertainty_variance", variance},
                          {"admitted", admit},
                          {"reason", gate ? d.reason : "no admission gate (no-gaps)"},
                          {"camera", camera_json(chosen[k].camera, chosen[k].id, "pseudo")}};
    if (d.structure) row["structure"] = *d.structure;
    entry["selection"].push_back(std::move(row));
    const auto path = inspection_path(entry["phase"].get<int>(), chosen[k].id, admit);
    if (!path.empty()) for_inspection.push_back({path, images[k]});
    if (!admit) {
      rejected.push_back(chosen[k].id);
      continue;
    }
    admitted_variances.push_back(variance);
    admitted_order.push_back(chosen[k].id);
    // no-gaps drops the gate, not the uncertainty weighting: the paper keeps the rest of the method.
    admitted[chosen[k].id] = {chosen[k].camera, image,
                              pseudo_pixel_weight(alpha, d.uncertainty, chosen[k].d_extrap, config_), chosen[k].id};
  }
  update_active_set(std::move(admitted), admitted_order, rejected, gate, entry);
  entry["admitted"] = admitted_variances.size();
  entry["mean_uncertainty_variance"] =
      admitted_variances.empty()
          ? 0.0
          : std::accumulate(admitted_variances.begin(), admitted_variances.end(), 0.0) / admitted_variances.size();
  // The tier follows the admitted views alone (sec. 3.4), unlike C_hist, which also remembers the rejected.
  if (gate) tier_ = next_tier(tier_, admitted_variances, config_);
  lap(entry, "admission", &clock);
  if (!for_inspection.empty()) {
    GAPS_RETURN_IF_ERROR(finish_inspection());
    for (auto& [path, image] : for_inspection) image = image.cpu();
    inspection_written_ =
        std::async(std::launch::async, [images = std::move(for_inspection)] { return write_pngs(images); });
    lap(entry, "inspection", &clock);
  }
  return absl::OkStatus();
}

void GapsTraining::update_active_set(std::map<int, PseudoView> admitted, const std::vector<int>& admitted_order,
                                     const std::vector<int>& rejected, bool gate, nlohmann::json& entry) {
  GapsConfig rules = config_;
  rules.refresh_active_set = gate && config_.refresh_active_set;  // no-gaps: generated once, never refreshed
  const ActiveSetChange change =
      refresh_active_set(active_phase_, admitted_order, rejected, entry["phase"].get<int>(), rules);
  entry["retired"] = nlohmann::json::array();
  for (const RetiredView& r : change.retired) {
    if (change.active.count(r.id) == 0) active_.erase(r.id);
    entry["retired"].push_back({{"id", r.id}, {"generated_in_phase", r.generated_in_phase}, {"reason", r.reason}});
  }
  for (int id : change.entered) {
    active_[id] = std::move(admitted.at(id));
    ever_admitted_.insert(id);
  }
  active_phase_ = change.active;
  entry["entered"] = change.entered;
  entry["refreshed"] = change.refreshed;
  entry["active"] = nlohmann::json::array();
  for (const auto& [id, born] : active_phase_) entry["active"].push_back(id);
}

absl::Status GapsTraining::finish_inspection() {
  if (inspection_written_.valid() && inspection_error_.ok()) inspection_error_ = inspection_written_.get();
  return inspection_error_;
}

}  // namespace gaps

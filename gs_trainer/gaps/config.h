#pragma once
// Hyperparameters of the GAPS method (paper sections 3.2-3.6): the alternating schedule, the candidate
// pool and its progressive tiers, the selection score, admission, the uncertainty-weighted pseudo loss,
// density-adaptive DropGaussian and the adaptive generation controls. Defaults are the paper's where it
// gives a value; where it leaves one open the choice is marked "(open)" and explained.
#include <vector>

#include <absl/status/status.h>
#include <nlohmann/json_fwd.hpp>
#include "common/option_table.h"
#include "gs_trainer/gaps/generator.h"

namespace gaps {

// Active pseudo-views per diffusion phase (paper sec. 4.3): 16 on LLFF, 24 on the wider 360° scenes. With
// n_active = 0 the run picks one of them from the training views' geometry (n_active_for).
inline constexpr int kNActiveLlff = 16;
inline constexpr int kNActiveMip360 = 24;

// X(type, name, default, min, max, help): see common/option_table.h. "(open)": the paper gives no value; the
// help says why ours.
// clang-format off
#define GAPS_GAPS_CONFIG_OPTIONS(X)                                                                                 \
  /* Schedule (sec. 3.2): a diffusion phase runs at every iteration t >= warmup with (t - warmup) % interval == 0. */ \
  X(int, warmup_iterations, 1000, 0, 1e6, "T_w: iterations before the first diffusion phase")                        \
  X(int, phase_interval, 500, 1, 1e6, "Delta T: iterations between diffusion phases")                               \
  X(int, async_iterations, 250, 0, 1e6,                                                                              \
    "not in the paper: iterations training goes on (on the views it has) while a phase's pseudo-views are "        \
    "generated from the model as the phase found it; they are judged and admitted after exactly this many, at the "  \
    "latest before the next phase, whatever the timing (0 = the phase waits for them, as in the paper; 250 costs "  \
    "no quality on fern 3 / 6 / 9 and bonsai 12 / 24, docs/results.md)")                                            \
  X(double, pseudo_probability, 0.25, 0, 1, "p_pseudo: chance an iteration trains on an admitted pseudo-view")       \
  /* Candidate pool (sec. 3.4, eq. slerp). */                                                                        \
  X(int, n_active, 0, 0, 1e4,                                                                                        \
    "pseudo-views selected per phase; 0 = from the training views' geometry, as --init auto decides: 16 for views " \
    "facing one way (LLFF), 24 for views surrounding the scene (Mip-NeRF 360)")                                      \
  X(std::vector<double>, tier_alpha_min, (std::vector<double>{0.0, -0.25, -0.5}), -10, 10,                          \
    "(open) lower ends of the progressive tiers' SLERP alpha ranges; tier k contains tier k-1, tier 0 contains "     \
    "[0, 1]: tier 0 interpolates, each later tier widens by a quarter baseline per side")                           \
  X(std::vector<double>, tier_alpha_max, (std::vector<double>{1.0, 1.25, 1.5}), -10, 10,                            \
    "(open) upper ends of the tiers' alpha ranges")                                                                  \
  X(double, alpha_step, 0.125, 1e-4, 1,                                                                              \
    "(open) alpha grid step; a fixed grid keeps candidate ids (and their history) across tier upgrades")            \
  X(double, max_extrap, 0.5, 0, 10, "hard cap on d_extrap = max(0, -alpha) + max(0, alpha - 1)")                    \
  X(bool, interpolate_intrinsics, true, 0, 0,                                                                        \
    "pseudo cameras lerp the pair's intrinsics (false: copy the first camera's)")                                    \
  X(double, tier_upgrade_variance, 0.01, 0, 1,                                                                       \
    "(open) upgrade the tier when the views admitted in a phase have a mean uncertainty variance below this: "    \
    "fern's first-phase reproject views measure 0.011-0.012 and views of a wrong pose 0.06-0.07, so the range "     \
    "widens once the views agree better with the model than at the start (docs/fidelity.md)")                     \
  X(int, tier_min_admitted, 1, 0, 1e6, "admitted views needed before a tier upgrade")                               \
  X(double, pose_rotation_weight, 0.5, 0, 1e6,                                                                       \
    "pose distance (eq. pose_dist) = ||c1 - c2|| + this times the geodesic angle in radians")                       \
  /* Score (eq. gaps_score, i_recon, c_gen, beta_anneal). */                                                         \
  X(double, beta_start, 2.0, 0, 100, "(open) beta at the first phase; the paper requires beta_start > beta_end")   \
  X(double, beta_end, 0.5, 0, 100, "(open) beta at the last phase")                                                  \
  X(double, w_sparsity, 0.2, 0, 100, "w_s on (1 - mean alpha) in I_recon")                                           \
  X(double, w_entropy, 0.2, 0, 100, "w_e on the normalised 3x3 local entropy in I_recon")                           \
  X(double, w_novelty, 0.6, 0, 100, "w_n on the novelty eta = min(1, novelty_gain * d / (1 + d)) in I_recon")       \
  X(double, novelty_gain, 4.0, 0, 1e6, "gain of the novelty term")                                                   \
  X(int, entropy_bins, 16, 2, 256, "(open) grey levels of the local entropy's histogram")                           \
  X(double, gamma_hist, 0.7, 0, 1, "gamma: C_gen = (1 - gamma) C_model + gamma C_hist")                             \
  X(double, w_init, 0.5, 0, 100, "(open) C_model = w_init C_init + w_ref C_ref")                                     \
  X(double, w_ref, 0.5, 0, 100, "(open) weight of C_ref in C_model")                                                 \
  X(double, init_coverage_weight, 0.5, 0, 1,                                                                         \
    "(open) C_init = this * coverage + (1 - this) * min(1, contrast / contrast_ref)")                                \
  X(double, contrast_ref, 0.25, 1e-6, 1e6, "(open) RMS luma contrast of a natural image, C_init's reference")       \
  X(double, coverage_alpha_threshold, 0.5, 0, 1, "(open) a pixel is covered when its rendered alpha reaches this") \
  X(double, ref_distance_scale, 0.5, 1e-9, 1e9, "C_ref = exp(-d_min_gt / scale)")                                    \
  X(double, hist_variance_scale, 0.3, 1e-9, 1e9,                                                                     \
    "C_hist = 1 - min(1, mean variance / scale), the mean over every earlier phase that generated the view")        \
  /* Selection (sec. 3.4 greedy selection, sec. 3.6 forced exploration). */                                          \
  X(double, diversity_radius, 0.15, 0, 1e6, "d_div: selected views lie at least this far apart (pose distance)")    \
  X(int, exploration_period, 3, 1, 1e6, "k_new: every k_new-th diffusion phase explores")                           \
  X(double, exploration_fraction, 0.25, 0, 1, "rho_new: this fraction of the selection goes to never-admitted views") \
  /* The active set (sec. 3.2 Stage II-III): the admitted views trained on. */                                         \
  X(bool, refresh_active_set, true, 0, 0,                                                                            \
    "(open) refresh the trained pseudo-views every phase: the phase's admitted views replace older ones, a view "   \
    "whose regeneration is rejected leaves, and so do views older than active_max_age phases or beyond "            \
    "active_size (false: every admitted view trains until the end)")                                                 \
  X(int, active_size, 0, 0, 1e4, "(open) most pseudo-views trained on at once; 0 = n_active")                        \
  X(int, active_max_age, 3, 0, 1e6,                                                                                  \
    "(open) a pseudo-view generated this many phases ago leaves the active set (0 = never by age); 3 = k_new, so "  \
    "no view outlives an exploration round")                                                                         \
  /* Admission and pseudo loss (sec. 3.6). */                                                                        \
  X(double, admit_min_alpha, 0.25, 0, 1, "tau_cov: admit when the render's mean alpha is at least this")            \
  X(double, admit_max_residual, 0.7, 0, 1, "tau_res: admit when mean |I_hall - I_GS| is below this")                \
  X(bool, admit_on_proposal, true, 0, 0,                                                                              \
    "not in the paper: judge what the generator proposes, I_GS + (I_hall - I_GS) / strength, on the covered "      \
    "pixels (false: I_hall itself on every pixel, the paper's literal reading, under which a generation anchored "   \
    "on the render passes whatever it added)")                                                                       \
  X(double, admit_min_structure, 0.4, -1, 1,                                                                         \
    "not in the paper: also require the mean SSIM of the judged image to the render >= this (0 = off); rejects "    \
    "noise, other scenes and wrong poses, which tau_res = 0.7 admits; 0.4 lies between fern's reproject views "   \
    "(0.54-0.56 at the first phase) and views of a pose half a baseline off (0.24-0.30; docs/fidelity.md)")                           \
  X(double, uncertainty_lambda, 0.7, 0, 1e6, "lambda_u (eq. confidence_weight)")                                     \
  X(double, uncertainty_eps, 1e-6, 1e-12, 1, "epsilon (eq. confidence_weight)")                                      \
  X(double, extrap_kappa, 2.0, 0, 1e6, "kappa (eq. extrap_decay)")                                                   \
  X(double, pseudo_loss_weight, 0.35, 0, 1e6, "w_PLW (eq. pseudo_loss)")                                             \
  /* Density-adaptive DropGaussian (eq. drop_ratio, dropgaussian). */                                                \
  X(double, drop_max, 0.2, 0, 0.99, "r_max: the largest drop ratio")                                                 \
  X(double, drop_n_ref, 200000, 1, 1e12, "N_thr: Gaussian count at which the drop ratio reaches r_max")             \
  X(double, drop_budget_fraction, 1.0, 0, 1e6,                                                                       \
    "not in the paper: with a Gaussian budget B, N_thr is min(N_thr, this * B), so that a model capped below "     \
    "N_thr still reaches r_max (0 = the paper's N_thr whatever the budget)")                                         \
  /* Generation controls (sec. 3.3), sent to the generator. */                                                       \
  X(double, strength_max, 0.85, 0, 1, "sigma_max (eq. adaptive_strength)")                                           \
  X(double, strength_min, 0.3, 0, 1, "sigma_min (eq. adaptive_strength)")                                            \
  X(double, cn_scale, 1.0, 0, 10, "mean ControlNet scale (eq. adaptive_cn)")                                         \
  X(double, cn_coverage, 0.3, 1e-6, 1, "tau_clip (eq. adaptive_cn)")                                                 \
  X(double, ip_adapter_scale, 0.5, 0, 10, "lambda_ip (eq. ipadapter)")                                               \
  X(int, lora_rank, 4, 1, 1024, "r (eq. lora)")                                                                      \
  X(int, lora_steps, 50, 0, 1e5, "LoRA training steps in the first diffusion phase (0 = no scene adaptation)")      \
  /* Two-stage generation (eq. two_stage), sent with every generation request. */                                   \
  X(double, inpaint_uncovered_fraction, 0.02, 0, 1,                                                                  \
    "views with more than this fraction of uncovered pixels go through SD2 inpainting (the paper's 2 %)")           \
  X(int, inpaint_dilation, 15, 1, 1001, "dilation kernel of the inpainting mask (odd; the paper's 15)")             \
  X(double, inpaint_depth_threshold, 0.01, 0, 1e12,                                                                  \
    "tau_d: pixels whose rendered depth (alpha-weighted distance) is below this are uncovered (not given by the "   \
    "paper; 0.01 marks pixels with almost no content where surfaces lie at distances of order 1)")
// clang-format on

struct GapsConfig {
  GAPS_GAPS_CONFIG_OPTIONS(GAPS_DECLARE_OPTION)

  int num_tiers() const { return static_cast<int>(tier_alpha_min.size()); }
};

// The two-stage settings every generation request carries.
inline InpaintSettings inpaint_settings(const GapsConfig& c) {
  return {c.inpaint_depth_threshold, c.inpaint_uncovered_fraction, c.inpaint_dilation};
}

// The scene adaptation the generator's adapt() is asked for (ip_adapter_scale travels with each request).
inline SceneAdaptation scene_adaptation(const GapsConfig& c) { return {c.lora_rank, c.lora_steps}; }

// Range checks from the option table, the tier layout (equal lengths, nested ranges containing [0, 1]) and
// the inpainting settings.
absl::Status validate_gaps_config(const GapsConfig& c);
// Every option of GapsConfig, in table order.
std::vector<OptionInfo> gaps_config_options();
// The pseudo-views per phase a run uses: c.n_active, or when 0 the paper's value for the views' layout.
int n_active_for(const GapsConfig& c, bool views_surround_scene);

// Index (0-based) of the diffusion phase that runs before iteration `iteration` (0-based, < total), or
// -1 when none does. With the defaults and T = 10,000: iterations 1000, 1500, ..., 9500, 18 phases.
int diffusion_phase_at(int iteration, int total_iterations, const GapsConfig& c);
int num_diffusion_phases(int total_iterations, const GapsConfig& c);
// The fewest total iterations with which a run has a diffusion phase at all (num_diffusion_phases >= 1).
int iterations_for_first_phase(const GapsConfig& c);

// Unknown keys and invalid values (validate_gaps_config) throw nlohmann::json::other_error.
void to_json(nlohmann::json& j, const GapsConfig& c);
void from_json(const nlohmann::json& j, GapsConfig& c);

}  // namespace gaps

#pragma once
// Hyperparameters of the GAPS method (paper sections 3.2-3.6): the alternating schedule, the candidate
// pool and its progressive tiers, the selection score, admission, the uncertainty-weighted pseudo loss,
// density-adaptive DropGaussian and the adaptive generation controls. Defaults are the paper's where it
// gives a value; where it leaves one open the choice is marked "(open)" and explained.
#include <vector>

#include <absl/status/status.h>
#include <nlohmann/json_fwd.hpp>
#include "gs_trainer/gaps/generator.h"

namespace gaps {

// Active pseudo-views per diffusion phase (paper sec. 4.3): 16 on LLFF, 24 on the wider 360° scenes.
inline constexpr int kNActiveLlff = 16;
inline constexpr int kNActiveMip360 = 24;

struct GapsConfig {
  // --- Schedule (sec. 3.2). A diffusion phase runs at every iteration t >= warmup with
  // (t - warmup) % phase_interval == 0; the total budget T is TrainConfig::iterations.
  int warmup_iterations = 1000;      // T_w
  int phase_interval = 500;          // ΔT
  double pseudo_probability = 0.25;  // p_pseudo: chance an iteration trains on an admitted pseudo-view

  // --- Candidate pool (sec. 3.4, eq:slerp).
  int n_active = kNActiveLlff;
  // Progressive tiers: tier k samples α in [tier_alpha_min[k], tier_alpha_max[k]]; each tier contains the
  // previous one. (open) The paper gives no numbers: tier 0 interpolates only, then the range widens by a
  // quarter baseline per side per tier, up to half a baseline beyond either camera.
  std::vector<double> tier_alpha_min = {0.0, -0.25, -0.5};
  std::vector<double> tier_alpha_max = {1.0, 1.25, 1.5};
  // (open) Uniform α grid: α = k * alpha_step. A fixed grid makes every tier's candidates a superset of
  // the previous tier's, so candidate ids (and their uncertainty history) survive tier upgrades.
  double alpha_step = 0.125;
  // Hard cap on d_extrap = max(0, -α) + max(0, α - 1), whatever the tiers say.
  double max_extrap = 0.5;
  // Intrinsics of a pseudo camera: lerped between the pair (true) or copied from the first camera.
  bool interpolate_intrinsics = true;
  // Tier upgrade: when at least tier_min_admitted pseudo-views are admitted and the mean of their
  // uncertainty variances (mean u², see admission.h) is below this. (open) 0.05 ≈ RMS residual 0.22,
  // i.e. C_hist ≈ 0.83 on the 0.3 scale of eq:c_gen.
  double tier_upgrade_variance = 0.05;
  int tier_min_admitted = 1;

  // --- Pose distance (eq:pose_dist): ||c1 - c2|| + pose_rotation_weight * geodesic angle (radians).
  double pose_rotation_weight = 0.5;

  // --- Score (eq:gaps_score, eq:i_recon, eq:c_gen, eq:beta_anneal).
  // (open) β values are not given; β_start > β_end as the paper requires.
  double beta_start = 2.0;
  double beta_end = 0.5;
  double w_sparsity = 0.2;  // w_s on (1 - mean alpha)
  double w_entropy = 0.2;   // w_e on the normalised 3x3 local entropy
  double w_novelty = 0.6;   // w_n on η = min(1, novelty_gain * d / (1 + d))
  double novelty_gain = 4.0;
  int entropy_bins = 16;    // (open) greyscale quantisation levels of the local entropy
  double gamma_hist = 0.7;  // γ: C_gen = (1 - γ) C_model + γ C_hist
  // C_model = w_init C_init + w_ref C_ref. (open) equal weights.
  double w_init = 0.5;
  double w_ref = 0.5;
  // (open) C_init = init_coverage_weight * coverage + (1 - init_coverage_weight) * min(1, contrast /
  // contrast_ref), contrast = std of the render's luma (RMS contrast); 0.25 is about a natural image's.
  double init_coverage_weight = 0.5;
  double contrast_ref = 0.25;
  // (open) coverage = fraction of pixels whose rendered alpha is at least this.
  double coverage_alpha_threshold = 0.5;
  double ref_distance_scale = 0.5;   // C_ref = exp(-d_min_gt / scale)
  double hist_variance_scale = 0.3;  // C_hist = 1 - min(1, σ̄² / scale)

  // --- Selection (sec. 3.4 greedy selection, sec. 3.6 forced exploration).
  double diversity_radius = 0.15;      // d_div, in pose distance
  int exploration_period = 3;          // k_new: every k_new-th diffusion phase explores
  double exploration_fraction = 0.25;  // ρ_new: ceil(ρ_new * |selection|) slots go to never-admitted views

  // --- Admission and pseudo loss (sec. 3.6).
  double admit_min_alpha = 0.25;    // τ_cov: mean alpha >= τ_cov
  double admit_max_residual = 0.7;  // τ_res: mean |I_hall - I_GS| < τ_res
  // Not in the paper: SSIM(I_hall, I_GS) >= this (0 disables). τ_res alone admits uniform noise (its mean
  // residual against a render is about 1/3); noise has an SSIM near 0 with any render, while a generation
  // anchored on the render keeps its structure. Low on purpose: it only rejects images without structure.
  double admit_min_structure = 0.1;
  double uncertainty_lambda = 0.7;   // λ_u (eq:confidence_weight)
  double uncertainty_eps = 1e-6;     // ε (eq:confidence_weight)
  double extrap_kappa = 2.0;         // κ (eq:extrap_decay)
  double pseudo_loss_weight = 0.35;  // w_PLW (eq:pseudo_loss)

  // --- Density-adaptive DropGaussian (eq:drop_ratio, eq:dropgaussian).
  double drop_max = 0.2;       // r_max
  double drop_n_ref = 200000;  // N_thr

  // --- Generation controls (sec. 3.3), consumed by the diffusion side.
  double strength_max = 0.85;     // σ_max (eq:adaptive_strength)
  double strength_min = 0.3;      // σ_min
  double cn_scale = 1.0;          // s̄_cn (eq:adaptive_cn)
  double cn_coverage = 0.3;       // τ_clip
  double ip_adapter_scale = 0.5;  // λ_ip (eq:ipadapter)
  int lora_rank = 4;              // r (eq:lora)
  int lora_steps = 50;            // LoRA steps in the first diffusion phase
  // Two-stage generation (eq:two_stage), sent with every generation request (GenerationRequest::inpaint).
  double inpaint_uncovered_fraction = InpaintSettings{}.uncovered_fraction;  // > 2% uncovered: SD2 inpainting
  int inpaint_dilation = InpaintSettings{}.dilation;  // dilation kernel of the inpainting mask (odd)
  // τ_d: render_depth (alpha-weighted distance) below this is uncovered. Not given by the paper; 0.01 marks
  // pixels with almost no rendered content in scenes whose surfaces lie at distances of order 1 or more.
  double inpaint_depth_threshold = InpaintSettings{}.depth_threshold;

  int num_tiers() const { return static_cast<int>(tier_alpha_min.size()); }
};

// The two-stage settings every generation request carries.
inline InpaintSettings inpaint_settings(const GapsConfig& c) {
  return {c.inpaint_depth_threshold, c.inpaint_uncovered_fraction, c.inpaint_dilation};
}

// The scene adaptation the generator's adapt() is asked for (ip_adapter_scale travels with each request).
inline SceneAdaptation scene_adaptation(const GapsConfig& c) { return {c.lora_rank, c.lora_steps}; }

// Checks ranges and the tier layout (equal lengths, nested ranges containing [0, 1]).
absl::Status validate_gaps_config(const GapsConfig& c);

// Index (0-based) of the diffusion phase that runs before iteration `iteration` (0-based, < total), or
// -1 when none does. With the defaults and T = 10,000: iterations 1000, 1500, ..., 9500, 18 phases.
int diffusion_phase_at(int iteration, int total_iterations, const GapsConfig& c);
int num_diffusion_phases(int total_iterations, const GapsConfig& c);

// Unknown keys and invalid values (validate_gaps_config) throw nlohmann::json::other_error.
void to_json(nlohmann::json& j, const GapsConfig& c);
void from_json(const nlohmann::json& j, GapsConfig& c);

}  // namespace gaps

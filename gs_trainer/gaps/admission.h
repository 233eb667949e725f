#pragma once
// Pseudo-view admission and the uncertainty-weighted pseudo loss weights (paper sec. 3.6), density-
// adaptive DropGaussian (sec. 3.5, eq:drop_ratio, eq:dropgaussian) and the coverage-adaptive generation
// controls (sec. 3.3, eq:adaptive_strength, eq:adaptive_cn). Images are H×W×3 in [0, 1], alpha maps H×W.
#include <cstdint>
#include <optional>
#include <string>

#include <ATen/Tensor.h>
#include <ATen/core/Generator.h>

#include "gs_trainer/gaps/config.h"

namespace gaps {

// eq:uncertainty per pixel: u(p) = |I_hall(p) - I_GS(p)|, a colour residual reduced to one value per
// pixel by the mean over the 3 channels (so u is in [0, 1] and the weight map is H×W). Returns H×W.
at::Tensor uncertainty_map(const at::Tensor& hallucinated, const at::Tensor& rendered);

// A view's uncertainty variance σ̄² (C_hist of eq:c_gen, the tier rule): mean of u² over its pixels,
// i.e. u read as a per-pixel standard deviation. (open) The paper names the quantity without a formula.
double uncertainty_variance(const at::Tensor& uncertainty);

struct AdmissionDecision {
  bool admitted = false;
  double mean_alpha = 0;            // ᾱ_v of the full-fidelity render
  double mean_residual = 0;         // mean |I - I_GS| over the judged pixels and channels (I: see admit_pseudo_view)
  std::optional<double> structure;  // mean SSIM(I, I_GS) over the judged pixels, when admit_min_structure > 0
  std::string reason;               // which criterion passed or failed, with the numbers
  at::Tensor uncertainty;           // H×W: u(p) = |I - I_GS| per pixel (eq:uncertainty), for the loss weights
};

// Dual-criterion admission (sec. 3.6): ᾱ_v >= admit_min_alpha and mean residual < admit_max_residual;
// admit_pseudo_view adds the structure criterion SSIM >= admit_min_structure (see config.h).
// Rejected views stay in the candidate pool (the caller keeps them; nothing here removes them).
AdmissionDecision decide_admission(double mean_alpha, double mean_residual, const GapsConfig& c);

// What the generator proposes at a view asked for with img2img strength σ: the render moved by the
// generator's change, undone of the anchoring, I_prop = clamp(I_GS + (I_hall - I_GS) / σ, 0, 1). An img2img
// generator keeps about (1 - σ) of the render, so the residual of I_hall itself shrinks with σ and says little
// about what the generator added; I_prop's residual is the disagreement between the generation (a warp, for
// `reproject`, exactly) and the render. σ below 0.05 counts as 0.05.
at::Tensor generator_proposal(const at::Tensor& hallucinated, const at::Tensor& rendered, double strength);

// The admission of one generated view. With admit_on_proposal (the default) the criteria judge
// generator_proposal(hallucinated, rendered, strength) over the covered pixels (render alpha >=
// coverage_alpha_threshold; all pixels when none is covered); without it, `hallucinated` over every pixel as
// the paper writes it. The decision carries the uncertainty map of the judged image.
AdmissionDecision admit_pseudo_view(const at::Tensor& hallucinated, const at::Tensor& rendered, const at::Tensor& alpha,
                                    const GapsConfig& c, double strength = 1.0);

// eq:confidence_weight: w(p) = α(p) (1 - λ_u u(p) / (max u + ε)). alpha and u are H×W.
at::Tensor confidence_weight(const at::Tensor& alpha, const at::Tensor& uncertainty, const GapsConfig& c);

// eq:extrap_decay: exp(-κ d_extrap).
double extrapolation_decay(double d_extrap, const GapsConfig& c);

// The whole per-pixel factor of eq:pseudo_loss: w_PLW · w_extrap(v) · w(p), H×W.
at::Tensor pseudo_pixel_weight(const at::Tensor& alpha, const at::Tensor& uncertainty, double d_extrap,
                               const GapsConfig& c);

// eq:drop_ratio: r = r_max · t/T · min(N_pts / N_thr, 1), t/T clamped to [0, 1]. With a Gaussian budget B > 0
// and drop_budget_fraction f > 0, N_thr is min(N_thr, f·B) (drop_threshold): a model capped below the
// paper's N_thr would otherwise never reach r_max.
double drop_ratio(int iteration, int total_iterations, int64_t num_gaussians, const GapsConfig& c,
                  int64_t gaussian_budget = 0);
double drop_threshold(const GapsConfig& c, int64_t gaussian_budget);

// eq:dropgaussian: an N-vector m_i / (1 - r), m_i ~ Bernoulli(1 - r), to multiply the opacities by.
// E[scale] = 1, so renders stay unbiased. r must be in [0, 1). `options` picks dtype and device (the
// generator must live on that device); the default is float32 on the CPU.
at::Tensor drop_gaussian_scale(int64_t num_gaussians, double ratio,
                               std::optional<at::Generator> generator = std::nullopt,
                               const at::TensorOptions& options = at::TensorOptions());

// eq:adaptive_strength: σ(v) = σ_max - coverage (σ_max - σ_min), coverage clamped to [0, 1].
double adaptive_strength(double coverage, const GapsConfig& c);

// eq:adaptive_cn: s_cn(v) = s̄_cn · min(1, coverage / τ_clip), coverage clamped at 0.
double adaptive_control_scale(double coverage, const GapsConfig& c);

}  // namespace gaps

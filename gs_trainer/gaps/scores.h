#pragma once
// Scoring and selection of Generative Active Pseudo-view Selection (paper sec. 3.4 and 3.6): render
// statistics, I_recon (eq:i_recon), C_gen (eq:c_gen), the annealed score (eq:gaps_score,
// eq:beta_anneal), greedy selection with a diversity radius and per-pair cap, forced exploration and the
// progressive-tier rule. Scores take per-candidate measurements, so they are testable without rendering.
#include <map>
#include <optional>
#include <vector>

#include <ATen/Tensor.h>

#include "gs_trainer/gaps/config.h"
#include "gs_trainer/gaps/pose.h"

namespace gaps {

// ---- Render statistics (inputs of the score). Images are H×W×3 in [0, 1]; alpha maps H×W.

// H_v of eq:i_recon per pixel, H×W in [0, 1]. (open) The luma is quantised to `bins` levels
// (bin = min(bins - 1, floor(luma * bins))); each pixel's Shannon entropy is taken over the histogram of
// its 3×3 window, windows clipped at the border (only in-image pixels count), and divided by the most a
// window of 9 pixels can reach, log2(min(9, bins)), so H shares the [0, 1] range of the other terms.
at::Tensor local_entropy_map(const at::Tensor& image, int bins);

// Fraction of pixels with alpha >= threshold: coverage(v) of eq:adaptive_cn / eq:adaptive_strength.
double coverage_fraction(const at::Tensor& alpha, double threshold);

// RMS contrast: the (population) standard deviation of the luma over all pixels.
double rms_contrast(const at::Tensor& image);

// Everything a candidate's score needs.
struct CandidateMeasurements {
  double mean_alpha = 0;        // ᾱ_v (eq:i_recon)
  double entropy_mean = 0;      // H_v, mean of local_entropy_map
  double coverage = 0;          // coverage_fraction(alpha, coverage_alpha_threshold)
  double contrast = 0;          // rms_contrast of the render
  double d_min_supervised = 0;  // min pose distance to the supervised views (GT and admitted pseudo): η
  double d_min_gt = 0;          // min pose distance to the ground-truth views: C_ref
  // σ̄²_v of eq:c_gen: mean_uncertainty_variance of the view's history; empty when it was never generated.
  std::optional<double> uncertainty_variance_history;
};

// Per candidate id, the uncertainty variance (uncertainty_variance in admission.h) of every diffusion phase
// that generated the view, in phase order. Rejected generations count as much as admitted ones: a view the
// diffusion model keeps failing on must lose confidence, or the score keeps selecting it.
using UncertaintyHistory = std::map<int, std::vector<double>>;

// σ̄²_v of eq:c_gen ("the mean uncertainty variance from prior phases"); empty when no phase generated `id`.
std::optional<double> mean_uncertainty_variance(const UncertaintyHistory& history, int id);

// The render terms of a batch of renders, images B×H×W×3 (clamped to [0, 1] first) and alphas B×H×W: B×4 doubles
// on their device, per render (ᾱ, mean H, coverage, contrast) as measure_render defines them. A candidate pool's
// statistics thus reach the host in one copy per batch instead of one per candidate. Float32 CUDA batches take one
// fused kernel (gaps/cuda/render_statistics.cu): the same definitions with sums in another order, within 1e-6 of
// these operations on the entropy term and 1e-9 on the others.
at::Tensor render_statistics(const at::Tensor& images, const at::Tensor& alphas, const GapsConfig& c);

// The measurements of one render from its row of render_statistics (4 doubles on the host) and the pose terms.
CandidateMeasurements measurements_from(const double* statistics, double d_min_supervised, double d_min_gt,
                                        std::optional<double> history);

// Fills the render terms of the measurements from a full-fidelity render (no DropGaussian).
CandidateMeasurements measure_render(const at::Tensor& image, const at::Tensor& alpha, double d_min_supervised,
                                     double d_min_gt, std::optional<double> history, const GapsConfig& c);

// ---- Score terms.

// η = min(1, novelty_gain * d / (1 + d)) (eq:i_recon).
double novelty(double d_min, const GapsConfig& c);
// I_recon = w_s (1 - ᾱ) + w_e H + w_n η (eq:i_recon).
double recon_informativeness(const CandidateMeasurements& m, const GapsConfig& c);
// (open) C_init = w_cov * coverage + (1 - w_cov) * min(1, contrast / contrast_ref) (sec. 3.4, "initial
// quality estimate based on Gaussian coverage and render contrast").
double initial_confidence(const CandidateMeasurements& m, const GapsConfig& c);
// C_ref = exp(-d_min_gt / ref_distance_scale).
double reference_confidence(double d_min_gt, const GapsConfig& c);
// C_model = w_init C_init + w_ref C_ref.
double model_confidence(const CandidateMeasurements& m, const GapsConfig& c);
// C_hist = 1 - min(1, σ̄² / hist_variance_scale).
double history_confidence(double mean_uncertainty_variance, const GapsConfig& c);
// C_gen = (1 - γ) C_model + γ C_hist (eq:c_gen). (open) Without history C_gen = C_model: γ weights
// history "after the first few phases", and an invented prior would bias unseen views.
double generative_confidence(const CandidateMeasurements& m, const GapsConfig& c);
// β(t) = β_start + (β_end - β_start) t / T (eq:beta_anneal), t / T clamped to [0, 1].
double annealed_beta(int iteration, int total_iterations, const GapsConfig& c);

struct ScoreTerms {
  double i_recon = 0, c_model = 0, c_gen = 0, beta = 0, score = 0;
};
// score = I_recon · C_gen^β (eq:gaps_score), with its terms for logging.
ScoreTerms score_candidate(const CandidateMeasurements& m, int iteration, int total_iterations, const GapsConfig& c);

// ---- Selection. Indices are positions in `pool`; scores[k] belongs to pool[k].

// Greedy (sec. 3.4): best score first; a candidate is skipped when it lies closer than diversity_radius
// (pose distance) to one already taken, or when its pair already gave ceil(n_active / n_pairs) views,
// n_pairs counting the distinct pairs in `pool`. Returns at most n_active indices in the order taken
// (descending score); fewer when the pool runs out. Ties keep pool order.
std::vector<int> select_greedy(const std::vector<Candidate>& pool, const std::vector<double>& scores,
                               const GapsConfig& c);

// Whether diffusion phase `phase` (0-based) forces exploration: every exploration_period-th phase, i.e.
// phases k-1, 2k-1, ... (sec. 3.6, "Mitigating admission saturation").
bool is_exploration_phase(int phase, const GapsConfig& c);

// Replaces the last ceil(exploration_fraction * |selected|) entries of `selected` (the lowest scores of a
// greedy selection) by the best-scoring candidates that were never admitted and not in `selected`,
// keeping the diversity radius to the views kept and added. (open) The per-pair cap is not applied: the
// point is to leave the pairs the selection already favours. If too few such candidates exist, the
// dropped views fill the remaining slots (in their order) so the batch does not shrink.
std::vector<int> force_exploration(const std::vector<Candidate>& pool, const std::vector<double>& scores,
                                   const std::vector<int>& selected, const GapsConfig& c);

// One diffusion phase's selection: select_greedy, then force_exploration on exploration phases.
std::vector<int> select_for_phase(const std::vector<Candidate>& pool, const std::vector<double>& scores, int phase,
                                  const GapsConfig& c);

// Progressive tiers (sec. 3.4): the next phase's tier. Upgrades by one when at least tier_min_admitted
// views are admitted and the mean of their uncertainty variances is below tier_upgrade_variance. The paper
// reads the signal off the admitted pseudo-views only: the caller passes the variances of the views the
// phase admitted, not the rejected ones that UncertaintyHistory also holds.
int next_tier(int current_tier, const std::vector<double>& admitted_uncertainty_variances, const GapsConfig& c);

}  // namespace gaps

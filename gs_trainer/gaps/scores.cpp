#include "gs_trainer/gaps/scores.h"

#include <ATen/ATen.h>

#include <algorithm>
#include <cmath>
#include <map>
#include <numeric>

#include "gs_trainer/eval/image_stats.h"
#include "gs_trainer/gaps/cuda/render_statistics_cuda.h"

namespace gaps {

namespace {

at::Tensor as_floating(const at::Tensor& t) { return t.is_floating_point() ? t : t.to(at::kFloat); }

// Shannon entropy (bits) of per-pixel histograms p: N×bins×H×W -> N×H×W. xlogy makes 0·log 0 = 0.
at::Tensor entropy_bits(const at::Tensor& p) { return -at::xlogy(p, p).sum(1) / std::log(2.0); }

// Positions of `scores` in descending order; stable, so ties keep pool order.
std::vector<int> by_descending_score(const std::vector<double>& scores) {
  std::vector<int> order(scores.size());
  std::iota(order.begin(), order.end(), 0);
  std::stable_sort(order.begin(), order.end(), [&](int a, int b) { return scores[a] > scores[b]; });
  return order;
}

// Closer than the diversity radius to a chosen view: the greedy step "removes" such candidates.
bool too_close(const std::vector<Candidate>& pool, const std::vector<int>& chosen, int k, const GapsConfig& c) {
  for (int s : chosen) {
    if (pose_distance(pool[k].camera, pool[s].camera, c.pose_rotation_weight) < c.diversity_radius) return true;
  }
  return false;
}

// ceil(n_active / n_pairs), n_pairs counting the distinct pairs present in the pool.
int per_pair_cap(const std::vector<Candidate>& pool, int n_active) {
  std::map<int, int> pairs;
  for (const Candidate& cand : pool) pairs[cand.pair_index] = 1;
  const int n_pairs = std::max<int>(1, static_cast<int>(pairs.size()));
  return (n_active + n_pairs - 1) / n_pairs;
}

void check_scores(const std::vector<Candidate>& pool, const std::vector<double>& scores) {
  TORCH_CHECK(scores.size() == pool.size(), "one score per candidate expected: ", scores.size(), " scores for ",
              pool.size(), " candidates");
}

}  // namespace

namespace {

// H_v maps of a batch of luma images B×H×W (local_entropy_map's definition): B×H×W.
at::Tensor entropy_maps(const at::Tensor& grey, int bins) {
  TORCH_CHECK(bins >= 2, "entropy needs at least 2 bins, got ", bins);
  const at::Tensor level = (grey * bins).floor().clamp(0, bins - 1);
  // B×bins×H×W codes, built in place rather than as one_hot's int64 B×H×W×bins and a transposed copy.
  const at::Tensor onehot =
      level.unsqueeze(1).eq(at::arange(bins, grey.options()).view({1, bins, 1, 1})).to(grey.scalar_type());
  // Mean of the one-hot codes over each 3×3 window = that window's histogram; count_include_pad = false
  // divides by the in-image pixels only (clipped windows at the border).
  const at::Tensor hist = at::avg_pool2d(onehot, {3, 3}, {1, 1}, {1, 1}, false, false);
  return entropy_bits(hist) / std::log2(std::min(9, bins));
}

// Per image of a batch (B×H×W or B×H×W×C), the mean over its pixels in double: B.
at::Tensor per_image_mean(const at::Tensor& t) { return t.flatten(1).to(at::kDouble).mean(1); }

at::Tensor coverage_fractions(const at::Tensor& alphas, double threshold) {
  return per_image_mean(alphas >= threshold);
}

at::Tensor rms_contrasts(const at::Tensor& images) {
  const at::Tensor grey = greyscale(images).flatten(1).to(at::kDouble);
  return (grey - grey.mean(1, /*keepdim=*/true)).square().mean(1).sqrt();
}

}  // namespace

at::Tensor local_entropy_map(const at::Tensor& image, int bins) {
  return entropy_maps(greyscale(image).unsqueeze(0), bins)[0];
}

double coverage_fraction(const at::Tensor& alpha, double threshold) {
  return coverage_fractions(alpha.unsqueeze(0), threshold).item<double>();
}

double rms_contrast(const at::Tensor& image) { return rms_contrasts(image.unsqueeze(0)).item<double>(); }

at::Tensor render_statistics(const at::Tensor& raw_images, const at::Tensor& alphas, const GapsConfig& c) {
  TORCH_CHECK(raw_images.dim() == 4 && raw_images.size(3) == 3 && alphas.dim() == 3 &&
                  raw_images.sizes().slice(0, 3) == alphas.sizes(),
              "render_statistics: expected B×H×W×3 images and B×H×W alphas, got ", raw_images.sizes(), " and ",
              alphas.sizes());
#if defined(GAPS_CUDA_KERNELS)
  if (raw_images.is_cuda() && raw_images.scalar_type() == at::kFloat && alphas.scalar_type() == at::kFloat) {
    const at::Tensor mean =
        backend::render_statistics_sums_cuda(raw_images, alphas, c.entropy_bins, c.coverage_alpha_threshold) /
        static_cast<double>(alphas.size(1) * alphas.size(2));
    const at::Tensor variance = (mean.select(1, 4) - mean.select(1, 3).square()).clamp_min(0);
    return at::stack({mean.select(1, 0), mean.select(1, 1), mean.select(1, 2), variance.sqrt()}, 1);
  }
#endif
  const at::Tensor images = raw_images.clamp(0, 1);
  return at::stack(
      {per_image_mean(as_floating(alphas)), per_image_mean(entropy_maps(greyscale(images), c.entropy_bins)),
       coverage_fractions(alphas, c.coverage_alpha_threshold), rms_contrasts(images)},
      1);
}

CandidateMeasurements measurements_from(const double* statistics, double d_min_supervised, double d_min_gt,
                                        std::optional<double> history) {
  CandidateMeasurements m;
  m.mean_alpha = statistics[0];
  m.entropy_mean = statistics[1];
  m.coverage = statistics[2];
  m.contrast = statistics[3];
  m.d_min_supervised = d_min_supervised;
  m.d_min_gt = d_min_gt;
  m.uncertainty_variance_history = history;
  return m;
}

CandidateMeasurements measure_render(const at::Tensor& image, const at::Tensor& alpha, double d_min_supervised,
                                     double d_min_gt, std::optional<double> history, const GapsConfig& c) {
  const at::Tensor stats = render_statistics(image.unsqueeze(0), alpha.unsqueeze(0), c).cpu().contiguous();
  return measurements_from(stats.data_ptr<double>(), d_min_supervised, d_min_gt, history);
}

std::optional<double> mean_uncertainty_variance(const UncertaintyHistory& history, int id) {
  const auto it = history.find(id);
  if (it == history.end() || it->second.empty()) return std::nullopt;
  return std::accumulate(it->second.begin(), it->second.end(), 0.0) / static_cast<double>(it->second.size());
}

double novelty(double d_min, const GapsConfig& c) { return std::min(1.0, c.novelty_gain * d_min / (1.0 + d_min)); }

double recon_informativeness(const CandidateMeasurements& m, const GapsConfig& c) {
  return c.w_sparsity * (1.0 - m.mean_alpha) + c.w_entropy * m.entropy_mean +
         c.w_novelty * novelty(m.d_min_supervised, c);
}

double initial_confidence(const CandidateMeasurements& m, const GapsConfig& c) {
  const double contrast = std::min(1.0, m.contrast / c.contrast_ref);
  return c.init_coverage_weight * m.coverage + (1.0 - c.init_coverage_weight) * contrast;
}

double reference_confidence(double d_min_gt, const GapsConfig& c) { return std::exp(-d_min_gt / c.ref_distance_scale); }

double model_confidence(const CandidateMeasurements& m, const GapsConfig& c) {
  return c.w_init * initial_confidence(m, c) + c.w_ref * reference_confidence(m.d_min_gt, c);
}

double history_confidence(double mean_uncertainty_variance, const GapsConfig& c) {
  return 1.0 - std::min(1.0, mean_uncertainty_variance / c.hist_variance_scale);
}

double generative_confidence(const CandidateMeasurements& m, const GapsConfig& c) {
  const double c_model = model_confidence(m, c);
  if (!m.uncertainty_variance_history) return c_model;
  return (1.0 - c.gamma_hist) * c_model + c.gamma_hist * history_confidence(*m.uncertainty_variance_history, c);
}

double annealed_beta(int iteration, int total_iterations, const GapsConfig& c) {
  const double progress =
      total_iterations > 0 ? std::clamp(static_cast<double>(iteration) / total_iterations, 0.0, 1.0) : 1.0;
  return c.beta_start + (c.beta_end - c.beta_start) * progress;
}

ScoreTerms score_candidate(const CandidateMeasurements& m, int iteration, int total_iterations, const GapsConfig& c) {
  ScoreTerms s;
  s.i_recon = recon_informativeness(m, c);
  s.c_model = model_confidence(m, c);
  s.c_gen = generative_confidence(m, c);
  s.beta = annealed_beta(iteration, total_iterations, c);
  s.score = s.i_recon * std::pow(std::max(0.0, s.c_gen), s.beta);
  return s;
}

std::vector<int> select_greedy(const std::vector<Candidate>& pool, const std::vector<double>& scores,
                               const GapsConfig& c) {
  check_scores(pool, scores);
  const int cap = per_pair_cap(pool, c.n_active);
  std::map<int, int> taken_per_pair;
  std::vector<int> chosen;
  for (int k : by_descending_score(scores)) {
    if (static_cast<int>(chosen.size()) >= c.n_active) break;
    if (taken_per_pair[pool[k].pair_index] >= cap || too_close(pool, chosen, k, c)) continue;
    chosen.push_back(k);
    ++taken_per_pair[pool[k].pair_index];
  }
  return chosen;
}

bool is_exploration_phase(int phase, const GapsConfig& c) {
  return phase >= 0 && (phase + 1) % c.exploration_period == 0;
}

std::vector<int> force_exploration(const std::vector<Candidate>& pool, const std::vector<double>& scores,
                                   const std::vector<int>& selected, const GapsConfig& c) {
  check_scores(pool, scores);
  const int n = static_cast<int>(selected.size());
  // ceil with a tolerance: 0.25 * 4 must give 1, not 2, despite rounding.
  const int n_replace = std::min(n, static_cast<int>(std::ceil(c.exploration_fraction * n - 1e-9)));
  std::vector<int> out(selected.begin(), selected.end() - n_replace);
  int added = 0;
  for (int k : by_descending_score(scores)) {
    if (added >= n_replace) break;
    if (pool[k].admitted_before || std::find(selected.begin(), selected.end(), k) != selected.end()) continue;
    if (too_close(pool, out, k, c)) continue;
    out.push_back(k);
    ++added;
  }
  // Pool out of never-admitted views: the dropped ones take the free slots back rather than shrink the batch.
  for (int i = n - n_replace; i < n && static_cast<int>(out.size()) < n; ++i) {
    if (!too_close(pool, out, selected[i], c)) out.push_back(selected[i]);
  }
  return out;
}

std::vector<int> select_for_phase(const std::vector<Candidate>& pool, const std::vector<double>& scores, int phase,
                                  const GapsConfig& c) {
  std::vector<int> selected = select_greedy(pool, scores, c);
  return is_exploration_phase(phase, c) ? force_exploration(pool, scores, selected, c) : selected;
}

int next_tier(int current_tier, const std::vector<double>& admitted_uncertainty_variances, const GapsConfig& c) {
  const int n = static_cast<int>(admitted_uncertainty_variances.size());
  if (current_tier + 1 >= c.num_tiers() || n == 0 || n < c.tier_min_admitted) return current_tier;
  const double mean =
      std::accumulate(admitted_uncertainty_variances.begin(), admitted_uncertainty_variances.end(), 0.0) / n;
  return mean < c.tier_upgrade_variance ? current_tier + 1 : current_tier;
}

}  // namespace gaps

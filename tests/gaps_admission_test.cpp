// GAPS admission, uncertainty weights, DropGaussian and the adaptive generation controls (paper sec. 3.3,
// 3.5, 3.6): hand-computed values for every formula, and the unbiasedness of the dropout compensation.
#include <ATen/ATen.h>
#include <ATen/CPUGeneratorImpl.h>
#include <gtest/gtest.h>

#include <cmath>
#include <string>

#include "gs_trainer/gaps/admission.h"
#include "gs_trainer/gaps/config.h"
#include "tests/sdxl_test_util.h"
#include "tests/test_util.h"

namespace gaps {
namespace {

using test::contains;

const at::TensorOptions kDouble = at::TensorOptions().dtype(at::kDouble);

// A smooth grey texture of size×size×3 in [0.1, 0.9], standing in for a render with structure.
at::Tensor textured_render(int64_t size) {
  const at::Tensor ramp = at::linspace(0.1, 0.9, size, kDouble);
  return (0.5 + 0.4 * at::sin(ramp.view({size, 1}) * 20) * at::cos(ramp.view({1, size}) * 15))
      .unsqueeze(2)
      .expand({size, size, 3})
      .contiguous();
}

// H×W×3 image with every channel of every pixel `value`.
at::Tensor flat(int64_t h, int64_t w, double value) { return at::full({h, w, 3}, value, kDouble); }

// ---------------------------------------------------------------- admission (sec. 3.6)

// The paper's two criteria as it writes them: I_hall itself, every pixel, no structure criterion.
GapsConfig paper_gate() {
  GapsConfig c;
  c.admit_on_proposal = false;
  c.admit_min_structure = 0;
  return c;
}

TEST(Admission, AcceptsCoveredConsistentViews) {
  const GapsConfig c = paper_gate();
  // Residual 0.125 everywhere, mean alpha 0.5.
  const AdmissionDecision d = admit_pseudo_view(flat(2, 2, 0.25), flat(2, 2, 0.125), at::full({2, 2}, 0.5, kDouble), c);
  EXPECT_TRUE(d.admitted) << d.reason;
  EXPECT_DOUBLE_EQ(d.mean_alpha, 0.5);
  EXPECT_DOUBLE_EQ(d.mean_residual, 0.125);
  EXPECT_TRUE(contains(d.reason, "admitted")) << d.reason;
}

TEST(Admission, RejectsLowCoverage) {
  const GapsConfig c = paper_gate();
  const AdmissionDecision d =
      admit_pseudo_view(flat(2, 2, 0.25), flat(2, 2, 0.125), at::full({2, 2}, 0.125, kDouble), c);
  EXPECT_FALSE(d.admitted);
  EXPECT_TRUE(contains(d.reason, "coverage")) << d.reason;
  EXPECT_FALSE(contains(d.reason, "consistency")) << d.reason;
  // The threshold itself passes: ᾱ >= τ_cov.
  EXPECT_TRUE(decide_admission(0.25, 0.1, c).admitted);
  EXPECT_FALSE(decide_admission(0.2499, 0.1, c).admitted);
}

TEST(Admission, RejectsInconsistentGenerations) {
  const GapsConfig c = paper_gate();
  const AdmissionDecision d = admit_pseudo_view(flat(2, 2, 1.0), flat(2, 2, 0.25), at::ones({2, 2}, kDouble), c);
  EXPECT_FALSE(d.admitted);
  EXPECT_DOUBLE_EQ(d.mean_residual, 0.75);
  EXPECT_TRUE(contains(d.reason, "consistency")) << d.reason;
  EXPECT_FALSE(contains(d.reason, "coverage")) << d.reason;
  // Strictly below τ_res: the threshold itself fails.
  EXPECT_FALSE(decide_admission(0.5, 0.7, c).admitted);
  EXPECT_TRUE(decide_admission(0.5, 0.6999, c).admitted);
}

TEST(Admission, BothFailuresAreReported) {
  const AdmissionDecision d = decide_admission(0.1, 0.9, GapsConfig{});
  EXPECT_FALSE(d.admitted);
  EXPECT_TRUE(contains(d.reason, "coverage")) << d.reason;
  EXPECT_TRUE(contains(d.reason, "consistency")) << d.reason;
}

// ---------------------------------------------------------------- uncertainty and weights

// Rendered image black; the hallucination differs per pixel by (0,0,0), (.5,.5,.5), (.75,0,0), (1,1,1),
// so u = [[0, 0.5], [0.25, 1]] (channel mean).
at::Tensor hallucination() {
  at::Tensor h = at::zeros({2, 2, 3}, kDouble);
  h[0][1].fill_(0.5);
  h[1][0][0] = 0.75;
  h[1][1].fill_(1.0);
  return h;
}

at::Tensor expected_u() { return at::tensor({0.0, 0.5, 0.25, 1.0}, kDouble).view({2, 2}); }

TEST(Uncertainty, ChannelMeanAbsoluteResidual) {
  const at::Tensor u = uncertainty_map(hallucination(), at::zeros({2, 2, 3}, kDouble));
  ASSERT_EQ(u.sizes(), (at::IntArrayRef{2, 2}));
  EXPECT_TRUE(at::allclose(u, expected_u(), 0, 1e-15));
  // Symmetric in its arguments.
  EXPECT_TRUE(at::allclose(uncertainty_map(at::zeros({2, 2, 3}, kDouble), hallucination()), u, 0, 1e-15));
  // σ̄² = mean u² = (0 + 0.25 + 0.0625 + 1) / 4.
  EXPECT_DOUBLE_EQ(uncertainty_variance(u), 0.328125);
}

TEST(Uncertainty, ConfidenceWeight) {
  const GapsConfig c;  // λ_u 0.7, ε 1e-6
  const at::Tensor alpha = at::tensor({1.0, 0.5, 1.0, 0.0}, kDouble).view({2, 2});
  const at::Tensor w = confidence_weight(alpha, expected_u(), c);
  // max u = 1: w = α (1 - 0.7 u / (1 + 1e-6)).
  EXPECT_NEAR(w[0][0].item<double>(), 1.0, 1e-12);                           // u = 0
  EXPECT_NEAR(w[0][1].item<double>(), 0.5 * (1 - 0.35 / 1.000001), 1e-12);   // ≈ 0.325
  EXPECT_NEAR(w[1][0].item<double>(), 1.0 * (1 - 0.175 / 1.000001), 1e-12);  // ≈ 0.825
  EXPECT_NEAR(w[1][1].item<double>(), 0.0, 1e-12);                           // no coverage
  EXPECT_NEAR(w[0][1].item<double>(), 0.325, 1e-6);
  EXPECT_NEAR(w[1][0].item<double>(), 0.825, 1e-6);
  // Where the residual is largest the weight is (1 - λ_u) of the alpha, never negative.
  const at::Tensor full = confidence_weight(at::ones({2, 2}, kDouble), expected_u(), c);
  EXPECT_NEAR(full[1][1].item<double>(), 0.3, 1e-6);
  // A perfect generation keeps the alpha as is (ε avoids 0/0).
  EXPECT_TRUE(at::allclose(confidence_weight(alpha, at::zeros({2, 2}, kDouble), c), alpha));
}

TEST(Uncertainty, ExtrapolationDecayAndTotalWeight) {
  const GapsConfig c;  // κ 2, w_PLW 0.35
  EXPECT_DOUBLE_EQ(extrapolation_decay(0.0, c), 1.0);
  EXPECT_NEAR(extrapolation_decay(0.25, c), std::exp(-0.5), 1e-15);
  EXPECT_NEAR(extrapolation_decay(0.5, c), std::exp(-1.0), 1e-15);
  const at::Tensor alpha = at::tensor({1.0, 0.5, 1.0, 0.0}, kDouble).view({2, 2});
  const at::Tensor total = pseudo_pixel_weight(alpha, expected_u(), 0.5, c);
  EXPECT_NEAR(total[0][0].item<double>(), 0.35 * std::exp(-1.0), 1e-12);
  EXPECT_NEAR(total[0][1].item<double>(), 0.35 * std::exp(-1.0) * 0.5 * (1 - 0.35 / 1.000001), 1e-12);
  EXPECT_NEAR(pseudo_pixel_weight(alpha, expected_u(), 0.0, c)[1][0].item<double>(), 0.35 * (1 - 0.175 / 1.000001),
              1e-12);
}

// ---------------------------------------------------------------- DropGaussian (eq:drop_ratio, eq:dropgaussian)

TEST(DropGaussian, RatioRampsWithTimeAndDensity) {
  const GapsConfig c;  // r_max 0.2, N_thr 200,000
  EXPECT_DOUBLE_EQ(drop_ratio(0, 10000, 500000, c), 0.0);
  EXPECT_DOUBLE_EQ(drop_ratio(5000, 10000, 100000, c), 0.2 * 0.5 * 0.5);  // below N_thr: scaled
  EXPECT_DOUBLE_EQ(drop_ratio(5000, 10000, 300000, c), 0.1);              // above: capped at 1
  EXPECT_DOUBLE_EQ(drop_ratio(10000, 10000, 200000, c), 0.2);
  EXPECT_DOUBLE_EQ(drop_ratio(10000, 10000, 400000, c), 0.2);
  EXPECT_DOUBLE_EQ(drop_ratio(10000, 10000, 50000, c), 0.05);
  EXPECT_DOUBLE_EQ(drop_ratio(10000, 10000, 0, c), 0.0);
}

// With a Gaussian budget below N_thr the threshold is the budget (times drop_budget_fraction), so a capped
// model reaches r_max; 0 keeps the paper's N_thr.
TEST(DropGaussian, TheThresholdFollowsABudgetBelowIt) {
  GapsConfig c;
  EXPECT_DOUBLE_EQ(drop_threshold(c, 0), 200000);       // no budget
  EXPECT_DOUBLE_EQ(drop_threshold(c, 55000), 55000);    // fern 3 views' automatic budget
  EXPECT_DOUBLE_EQ(drop_threshold(c, 500000), 200000);  // a budget above N_thr changes nothing
  EXPECT_DOUBLE_EQ(drop_ratio(10000, 10000, 55000, c, 55000), 0.2);
  EXPECT_DOUBLE_EQ(drop_ratio(5000, 10000, 27500, c, 55000), 0.2 * 0.5 * 0.5);
  c.drop_budget_fraction = 0.5;
  EXPECT_DOUBLE_EQ(drop_threshold(c, 55000), 27500);
  c.drop_budget_fraction = 0;
  EXPECT_DOUBLE_EQ(drop_ratio(10000, 10000, 55000, c, 55000), 0.2 * 55000 / 200000);
}

TEST(DropGaussian, ScaleIsZeroOrCompensated) {
  at::Generator gen = at::make_generator<at::CPUGeneratorImpl>(7);
  const at::Tensor s = drop_gaussian_scale(1000, 0.2, gen);
  EXPECT_EQ(s.scalar_type(), at::kFloat);
  ASSERT_EQ(s.sizes(), (at::IntArrayRef{1000}));
  const at::Tensor dropped = s == 0;
  const at::Tensor kept = (s - 1.25).abs() < 1e-6;
  EXPECT_TRUE((dropped | kept).all().item<bool>());
  EXPECT_TRUE(at::equal(drop_gaussian_scale(10, 0.0, gen), at::ones({10}, at::kFloat)));
  EXPECT_EQ(drop_gaussian_scale(4, 0.1, gen, kDouble).scalar_type(), at::kDouble);
  EXPECT_THROW(drop_gaussian_scale(4, 1.0, gen), c10::Error);
}

TEST(DropGaussian, CompensationIsUnbiased) {
  // Each entry is 0 with probability r and 1/(1-r) otherwise: mean 1, variance r / (1 - r). The mean of
  // n entries has standard deviation sqrt(r / ((1 - r) n)); 5 of those is the tolerance, which a correct
  // implementation misses with probability < 1e-6 (and the seed is fixed). Without the compensation the
  // mean would be 1 - r, hundreds of standard deviations away.
  const int64_t n = 2'000'000;
  at::Generator gen = at::make_generator<at::CPUGeneratorImpl>(12345);
  for (double r : {0.05, 0.2, 0.5}) {
    const at::Tensor s = drop_gaussian_scale(n, r, gen, kDouble);
    const double sd = std::sqrt(r / ((1 - r) * n));
    EXPECT_NEAR(s.mean().item<double>(), 1.0, 5 * sd) << "r = " << r;
    // And the drop frequency is r (binomial standard deviation sqrt(r (1 - r) / n)).
    EXPECT_NEAR((s == 0).to(at::kDouble).mean().item<double>(), r, 5 * std::sqrt(r * (1 - r) / n)) << "r = " << r;
  }
}

// ---------------------------------------------------------------- generation controls (sec. 3.3)

TEST(GenerationControls, AdaptiveStrength) {
  const GapsConfig c;  // σ 0.85 -> 0.3
  EXPECT_DOUBLE_EQ(adaptive_strength(0.0, c), 0.85);
  EXPECT_NEAR(adaptive_strength(0.3, c), 0.85 - 0.3 * 0.55, 1e-15);  // 0.685
  EXPECT_NEAR(adaptive_strength(0.3, c), 0.685, 1e-12);
  EXPECT_NEAR(adaptive_strength(1.0, c), 0.3, 1e-15);
  EXPECT_NEAR(adaptive_strength(1.5, c), 0.3, 1e-15);  // coverage is a fraction
}

TEST(GenerationControls, AdaptiveControlScale) {
  const GapsConfig c;  // s̄ 1.0, τ_clip 0.3
  EXPECT_DOUBLE_EQ(adaptive_control_scale(0.0, c), 0.0);
  EXPECT_NEAR(adaptive_control_scale(0.15, c), 0.5, 1e-15);
  EXPECT_DOUBLE_EQ(adaptive_control_scale(0.3, c), 1.0);
  EXPECT_DOUBLE_EQ(adaptive_control_scale(1.0, c), 1.0);
  GapsConfig half = c;
  half.cn_scale = 0.5;
  EXPECT_DOUBLE_EQ(adaptive_control_scale(1.0, half), 0.5);
}

// ---------------------------------------------------------------- structure guard (not in the paper)

// A smooth textured "render" and uniform noise: the noise passes τ_res = 0.7 (mean residual about 1/3), so
// only the structure guard stops it; a generation that keeps the render's structure passes it.
TEST(StructureGuard, RejectsNoiseThatTheResidualCriterionAdmits) {
  GapsConfig c;
  c.admit_min_structure = 0.1;  // off by default (the paper's two criteria); a guard against garbage generators
  constexpr int64_t kSize = 128;
  const at::Tensor render = textured_render(kSize);
  const at::Tensor alpha = at::ones({kSize, kSize}, kDouble);
  at::manual_seed(3);
  const at::Tensor noise = at::rand({kSize, kSize, 3}, kDouble);
  const AdmissionDecision rejected = admit_pseudo_view(noise, render, alpha, c);
  EXPECT_LT(rejected.mean_residual, c.admit_max_residual);
  ASSERT_TRUE(rejected.structure.has_value());
  EXPECT_LT(*rejected.structure, c.admit_min_structure);
  EXPECT_FALSE(rejected.admitted);
  EXPECT_TRUE(contains(rejected.reason, "rejected: structure (SSIM to the render")) << rejected.reason;

  const AdmissionDecision kept = admit_pseudo_view((render * 0.9 + 0.05).contiguous(), render, alpha, c);
  EXPECT_TRUE(kept.admitted) << kept.reason;
  EXPECT_GT(*kept.structure, 0.5);
  EXPECT_TRUE(contains(kept.reason, "SSIM to the render")) << kept.reason;

  GapsConfig off = c;
  off.admit_min_structure = 0;
  const AdmissionDecision paper_only = admit_pseudo_view(noise, render, alpha, off);
  EXPECT_TRUE(paper_only.admitted) << paper_only.reason;
  EXPECT_FALSE(paper_only.structure.has_value());
}

// ---------------------------------------------------------------- the generator's proposal (not in the paper)

TEST(Proposal, UndoesTheAnchoringOfAnImg2ImgBlend) {
  at::manual_seed(4);
  const at::Tensor render = at::rand({6, 5, 3}, kDouble) * 0.5 + 0.25;
  const at::Tensor warp = at::rand({6, 5, 3}, kDouble) * 0.5 + 0.25;
  const at::Tensor blend = 0.7 * render + 0.3 * warp;  // strength 0.3
  test::expect_close(generator_proposal(blend, render, 0.3), warp, 1e-12, "proposal of a blend");
  // Clamped to [0, 1]; strengths below 0.05 count as 0.05.
  const at::Tensor far = generator_proposal(flat(2, 2, 1.0), flat(2, 2, 0.5), 0.1);
  EXPECT_DOUBLE_EQ(far.min().item<double>(), 1.0);
  test::expect_close(generator_proposal(flat(2, 2, 0.51), flat(2, 2, 0.5), 0.0), flat(2, 2, 0.7), 1e-12, "floor");
}

// Noise mixed into the render at strength 0.3, as a blending generator would return it: the paper's literal
// criteria see a residual of about 0.1 and admit it; judged on the proposal (the noise itself) it fails.
TEST(Proposal, ABlendOfNoiseIsRejectedThoughItsOwnResidualIsSmall) {
  constexpr int64_t kSize = 96;
  const at::Tensor render = textured_render(kSize);
  const at::Tensor alpha = at::ones({kSize, kSize}, kDouble);
  at::manual_seed(6);
  const at::Tensor blend = 0.7 * render + 0.3 * at::rand({kSize, kSize, 3}, kDouble);
  const AdmissionDecision literal = admit_pseudo_view(blend, render, alpha, paper_gate(), 0.3);
  EXPECT_TRUE(literal.admitted) << literal.reason;
  EXPECT_LT(literal.mean_residual, 0.15);
  const GapsConfig c;
  const AdmissionDecision judged = admit_pseudo_view(blend, render, alpha, c, 0.3);
  EXPECT_FALSE(judged.admitted) << judged.reason;
  EXPECT_GT(judged.mean_residual, 0.25);
  EXPECT_TRUE(contains(judged.reason, "structure")) << judged.reason;
  // The uncertainty map is the proposal's residual: the noise's distance from the render, not 0.3 of it.
  test::expect_close(judged.uncertainty, (generator_proposal(blend, render, 0.3) - render).abs().mean(2), 1e-12,
                     "uncertainty of the proposal");
  // A blend towards a slightly brighter render keeps its structure and passes.
  const AdmissionDecision kept = admit_pseudo_view(0.7 * render + 0.3 * (render * 0.9 + 0.08), render, alpha, c, 0.3);
  EXPECT_TRUE(kept.admitted) << kept.reason;
}

// Only covered pixels (alpha >= coverage_alpha_threshold) are judged: a hole the generator filled with
// anything does not count against the view.
TEST(Proposal, UncoveredPixelsAreNotJudged) {
  GapsConfig c;
  c.admit_min_structure = 0;
  at::Tensor alpha = at::ones({4, 4}, kDouble);
  alpha.slice(1, 0, 2).fill_(0.1);  // the left half uncovered
  at::Tensor image = flat(4, 4, 0.5);
  image.slice(1, 0, 2).fill_(1.0);  // residual 0.5 there, 0 elsewhere
  const AdmissionDecision d = admit_pseudo_view(image, flat(4, 4, 0.5), alpha, c, 1.0);
  EXPECT_DOUBLE_EQ(d.mean_residual, 0.0);
  EXPECT_DOUBLE_EQ(admit_pseudo_view(image, flat(4, 4, 0.5), alpha, paper_gate(), 1.0).mean_residual, 0.25);
}

}  // namespace
}  // namespace gaps

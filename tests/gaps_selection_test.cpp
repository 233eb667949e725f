// GAPS pose maths, scores and selection (paper sec. 3.2 schedule, 3.4): hand-computed values for every
// formula, and small candidate pools whose greedy order is known by construction.
#include <ATen/ATen.h>
#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <functional>
#include <set>
#include <string>
#include <vector>

#include <Eigen/Geometry>
#include <nlohmann/json.hpp>

#include "gs_trainer/eval/image_stats.h"
#include "gs_trainer/gaps/config.h"
#include "gs_trainer/gaps/pose.h"
#include "gs_trainer/gaps/scores.h"

namespace gaps {
namespace {

constexpr double kPi = 3.14159265358979323846;
const at::TensorOptions kDouble = at::TensorOptions().dtype(at::kDouble);

Eigen::Matrix3d rot_y(double angle) { return Eigen::AngleAxisd(angle, Eigen::Vector3d::UnitY()).toRotationMatrix(); }

Eigen::Matrix3d rot(double angle, const Eigen::Vector3d& axis) {
  return Eigen::AngleAxisd(angle, axis.normalized()).toRotationMatrix();
}

// World-to-camera R and a centre c (t = -R c), 64×48 with fx = fy = 100.
Camera make_camera(const Eigen::Matrix3d& R, const Eigen::Vector3d& centre, double f = 100.0) {
  Camera cam;
  cam.name = "cam";
  cam.width = 64;
  cam.height = 48;
  cam.fx = cam.fy = f;
  cam.cx = 32;
  cam.cy = 24;
  cam.R = R;
  cam.t = -R * centre;
  return cam;
}

void expect_matrix_near(const Eigen::Matrix3d& a, const Eigen::Matrix3d& b, double tol) {
  EXPECT_LT((a - b).cwiseAbs().maxCoeff(), tol) << "\n" << a << "\nvs\n" << b;
}

void expect_vector_near(const Eigen::Vector3d& a, const Eigen::Vector3d& b, double tol) {
  EXPECT_LT((a - b).cwiseAbs().maxCoeff(), tol) << a.transpose() << " vs " << b.transpose();
}

// ---------------------------------------------------------------- config and schedule

TEST(GapsConfig, DefaultsAreThePapers) {
  const GapsConfig c;
  EXPECT_EQ(c.warmup_iterations, 1000);
  EXPECT_EQ(c.phase_interval, 500);
  EXPECT_DOUBLE_EQ(c.pseudo_probability, 0.25);
  EXPECT_EQ(c.n_active, 0);  // the paper's 16 or 24, from the training views' layout (n_active_for)
  EXPECT_EQ(kNActiveLlff, 16);
  EXPECT_EQ(kNActiveMip360, 24);
  EXPECT_DOUBLE_EQ(c.admit_min_alpha, 0.25);    // tau_cov
  EXPECT_DOUBLE_EQ(c.admit_max_residual, 0.7);  // tau_res
  // Departures (docs/fidelity.md): the gate judges the generator's proposal and its structure.
  EXPECT_TRUE(c.admit_on_proposal);
  EXPECT_GT(c.admit_min_structure, 0.0);
  EXPECT_EQ(c.lora_rank, 4);
  EXPECT_EQ(c.lora_steps, 50);
  EXPECT_DOUBLE_EQ(c.ip_adapter_scale, 0.5);
  EXPECT_DOUBLE_EQ(c.w_sparsity + c.w_entropy + c.w_novelty, 1.0);
  EXPECT_DOUBLE_EQ(c.gamma_hist, 0.7);
  EXPECT_DOUBLE_EQ(c.diversity_radius, 0.15);
  EXPECT_EQ(c.exploration_period, 3);
  EXPECT_DOUBLE_EQ(c.exploration_fraction, 0.25);
  EXPECT_GT(c.beta_start, c.beta_end);  // eq:beta_anneal requires β_start > β_end
  EXPECT_TRUE(validate_gaps_config(c).ok());
}

TEST(GapsConfig, JsonRoundTripAndUnknownKeyIsAnError) {
  GapsConfig c;
  c.n_active = kNActiveMip360;
  c.tier_alpha_min = {0.0, -0.5};
  c.tier_alpha_max = {1.0, 1.5};
  c.beta_end = 0.25;
  const nlohmann::json j = c;
  const GapsConfig back = j.get<GapsConfig>();
  EXPECT_EQ(back.n_active, 24);
  EXPECT_EQ(back.tier_alpha_min, c.tier_alpha_min);
  EXPECT_EQ(back.tier_alpha_max, c.tier_alpha_max);
  EXPECT_DOUBLE_EQ(back.beta_end, 0.25);
  EXPECT_EQ(nlohmann::json(back), j);

  EXPECT_THROW(nlohmann::json({{"n_activ", 3}}).get<GapsConfig>(), nlohmann::json::other_error);
  // Partial objects keep the other defaults.
  EXPECT_EQ(nlohmann::json({{"diversity_radius", 0.3}}).get<GapsConfig>().n_active, 0);
}

TEST(GapsConfig, InvalidTiersAreRejected) {
  // Tier 1 must contain tier 0.
  EXPECT_THROW((nlohmann::json({{"tier_alpha_min", nlohmann::json::array({0.0, 0.1})},
                                {"tier_alpha_max", nlohmann::json::array({1.0, 1.2})}})
                    .get<GapsConfig>()),
               nlohmann::json::other_error);
  // Unequal lengths.
  EXPECT_THROW((nlohmann::json({{"tier_alpha_min", nlohmann::json::array({0.0})}}).get<GapsConfig>()),
               nlohmann::json::other_error);
  GapsConfig c;
  c.drop_max = 1.0;  // 1/(1-r) would divide by zero
  EXPECT_FALSE(validate_gaps_config(c).ok());
}

// The generator-side controls are the paper's by default (sec. 3.3: LoRA rank 4, 50 steps, lambda_ip 0.5)
// and a job with values out of range is refused before any generator sees them.
TEST(GapsConfig, GenerationControlsArePapersAndChecked) {
  GapsConfig c;
  EXPECT_EQ(scene_adaptation(c).lora_rank, 4);
  EXPECT_EQ(scene_adaptation(c).lora_steps, 50);
  EXPECT_DOUBLE_EQ(c.ip_adapter_scale, 0.5);
  const auto refusal = [](const std::function<void(GapsConfig&)>& change) {
    GapsConfig bad;
    change(bad);
    return std::string(validate_gaps_config(bad).message());
  };
  EXPECT_NE(refusal([](GapsConfig& g) { g.lora_rank = 0; }).find("option 'lora_rank' = 0 is outside [1, 1024]"),
            std::string::npos);
  EXPECT_NE(refusal([](GapsConfig& g) { g.lora_steps = -1; }).find("option 'lora_steps' = -1 is outside [0, 100000]"),
            std::string::npos);
  EXPECT_NE(refusal([](GapsConfig& g) { g.ip_adapter_scale = -0.1; }).find("ip_adapter_scale"), std::string::npos);
  EXPECT_TRUE(refusal([](GapsConfig& g) { g.lora_steps = 0; }).empty()) << "no scene adaptation is allowed";
}

TEST(GapsSchedule, PhasesEveryIntervalAfterWarmup) {
  const GapsConfig c;
  EXPECT_EQ(diffusion_phase_at(0, 10000, c), -1);
  EXPECT_EQ(diffusion_phase_at(999, 10000, c), -1);
  EXPECT_EQ(diffusion_phase_at(1000, 10000, c), 0);
  EXPECT_EQ(diffusion_phase_at(1200, 10000, c), -1);
  EXPECT_EQ(diffusion_phase_at(1500, 10000, c), 1);
  EXPECT_EQ(diffusion_phase_at(9500, 10000, c), 17);
  EXPECT_EQ(diffusion_phase_at(10000, 10000, c), -1);
  // Sec. 3.2: "approximately 18 diffusion phases" for T = 10,000.
  EXPECT_EQ(num_diffusion_phases(10000, c), 18);
  EXPECT_EQ(num_diffusion_phases(1000, c), 0);
  EXPECT_EQ(num_diffusion_phases(1001, c), 1);
  EXPECT_EQ(num_diffusion_phases(iterations_for_first_phase(c) - 1, c), 0);
  EXPECT_EQ(num_diffusion_phases(iterations_for_first_phase(c), c), 1);
}

// ---------------------------------------------------------------- pose distance (eq:pose_dist)

TEST(PoseDistance, IdenticalPosesAreZeroApart) {
  const Camera a = make_camera(rot(0.7, {1, 2, 3}), {0.5, -1, 2});
  EXPECT_NEAR(pose_distance(a, a), 0.0, 1e-12);
  const Camera id = make_camera(Eigen::Matrix3d::Identity(), Eigen::Vector3d::Zero());
  EXPECT_NEAR(pose_distance(id, id), 0.0, 1e-12);
}

TEST(PoseDistance, PureTranslationIsTheCentreDistance) {
  const Eigen::Matrix3d R = rot(0.3, {0, 1, 1});
  const Camera a = make_camera(R, {0, 0, 0});
  const Camera b = make_camera(R, {3, 4, 0});
  EXPECT_NEAR(pose_distance(a, b), 5.0, 1e-12);
  EXPECT_NEAR(pose_distance(b, a), 5.0, 1e-12);
}

TEST(PoseDistance, PureRotationIsHalfTheAngle) {
  const Eigen::Vector3d c(1, 2, 3);
  const Camera a = make_camera(Eigen::Matrix3d::Identity(), c);
  const Camera b = make_camera(rot_y(kPi / 2), c);
  // 0.5 · arccos((tr(R1ᵀR2) - 1) / 2) = 0.5 · π/2 (the centres coincide although the t's differ).
  EXPECT_NEAR(pose_distance(a, b), kPi / 4, 1e-12);
  EXPECT_NEAR(pose_distance(a, b, 1.0), kPi / 2, 1e-12);
  // A tiny angle, where the arccos form loses half its digits.
  const Camera tiny = make_camera(rot_y(1e-7), c);
  EXPECT_NEAR(pose_distance(a, tiny), 0.5e-7, 1e-15);
}

TEST(PoseDistance, TranslationAndRotationAdd) {
  const Camera a = make_camera(Eigen::Matrix3d::Identity(), {0, 0, 0});
  const Camera b = make_camera(rot_y(kPi), {0, 0, 2});
  EXPECT_NEAR(pose_distance(a, b), 2.0 + 0.5 * kPi, 1e-9);
  const std::vector<Camera> others = {b, make_camera(Eigen::Matrix3d::Identity(), {0, 1, 0})};
  EXPECT_NEAR(min_pose_distance(a, others), 1.0, 1e-12);
  EXPECT_TRUE(std::isinf(min_pose_distance(a, {})));
}

// ---------------------------------------------------------------- interpolation (eq:slerp)

TEST(Slerp, EndpointsAreTheCameras) {
  const Camera a = make_camera(rot(0.4, {1, 0, 1}), {0, 0, 0}, 100);
  const Camera b = make_camera(rot(-0.9, {0, 1, 2}), {2, 1, 0}, 200);
  const Camera at0 = interpolate_camera(a, b, 0.0);
  const Camera at1 = interpolate_camera(a, b, 1.0);
  expect_matrix_near(at0.R, a.R, 1e-12);
  expect_vector_near(at0.t, a.t, 1e-12);
  expect_matrix_near(at1.R, b.R, 1e-12);
  expect_vector_near(at1.t, b.t, 1e-12);
  EXPECT_NEAR(at0.fx, 100, 1e-12);
  EXPECT_NEAR(at1.fx, 200, 1e-12);
}

TEST(Slerp, MidpointIsOrthonormalHalfwayAndCentred) {
  const Camera a = make_camera(Eigen::Matrix3d::Identity(), {0, 0, 0}, 100);
  const Camera b = make_camera(rot_y(kPi / 2), {2, 0, 0}, 200);
  const Camera m = interpolate_camera(a, b, 0.5);
  expect_matrix_near(m.R * m.R.transpose(), Eigen::Matrix3d::Identity(), 1e-12);
  EXPECT_NEAR(m.R.determinant(), 1.0, 1e-12);
  expect_matrix_near(m.R, rot_y(kPi / 4), 1e-12);  // R_a (R_aᵀ R_b)^½ = rot_y(45°)
  expect_vector_near(m.center(), Eigen::Vector3d(1, 0, 0), 1e-12);
  EXPECT_NEAR(m.fx, 150, 1e-12);
  EXPECT_NEAR(m.fy, 150, 1e-12);
  // On the geodesic: equally far from both ends.
  EXPECT_NEAR(pose_distance(m, a), pose_distance(m, b), 1e-12);
  EXPECT_EQ(m.width, 64);
  EXPECT_TRUE(m.image_path.empty());
}

TEST(Slerp, ExtrapolatesBeyondThePair) {
  const Camera a = make_camera(Eigen::Matrix3d::Identity(), {0, 0, 0});
  const Camera b = make_camera(rot_y(kPi / 2), {2, 0, 0});
  const Camera past_b = interpolate_camera(a, b, 1.5);
  expect_matrix_near(past_b.R, rot_y(3 * kPi / 4), 1e-12);
  expect_vector_near(past_b.center(), Eigen::Vector3d(3, 0, 0), 1e-12);
  const Camera before_a = interpolate_camera(a, b, -0.5);
  expect_matrix_near(before_a.R, rot_y(-kPi / 4), 1e-12);
  expect_vector_near(before_a.center(), Eigen::Vector3d(-1, 0, 0), 1e-12);
  EXPECT_DOUBLE_EQ(extrapolation_distance(1.5), 0.5);
  EXPECT_DOUBLE_EQ(extrapolation_distance(-0.5), 0.5);
  EXPECT_DOUBLE_EQ(extrapolation_distance(0.3), 0.0);
  EXPECT_DOUBLE_EQ(extrapolation_distance(1.0), 0.0);
}

TEST(Slerp, GeneralRotationsFollowThePowerLaw) {
  // α = 2: R_a (R_aᵀ R_b)² = R_b R_aᵀ R_b, independent of how the power is computed.
  const Camera a = make_camera(rot(0.5, {1, 2, 3}), {0, 0, 0});
  const Camera b = make_camera(rot(1.1, {-2, 1, 0.5}), {1, 1, 1});
  const Camera two = interpolate_camera(a, b, 2.0);
  expect_matrix_near(two.R, b.R * a.R.transpose() * b.R, 1e-12);
  expect_vector_near(two.center(), Eigen::Vector3d(2, 2, 2), 1e-12);
}

TEST(Slerp, IntrinsicsFromTheFirstOrRescaledAndLerped) {
  const Camera a = make_camera(Eigen::Matrix3d::Identity(), {0, 0, 0}, 100);
  Camera b = make_camera(Eigen::Matrix3d::Identity(), {1, 0, 0}, 300);
  EXPECT_NEAR(interpolate_camera(a, b, 0.5, /*interpolate_intrinsics=*/false).fx, 100, 1e-12);
  // b at twice the size: rescaled to a's size its focal length is 300 again, so the midpoint has 200.
  b = b.resized(128, 96);
  EXPECT_NEAR(b.fx, 600, 1e-12);
  const Camera m = interpolate_camera(a, b, 0.5);
  EXPECT_EQ(m.width, 64);
  EXPECT_NEAR(m.fx, 0.5 * (100 + 300), 1e-12);
  EXPECT_NEAR(m.cx, 32, 1e-12);
}

// ---------------------------------------------------------------- candidate pool and tiers

std::vector<Camera> three_cameras() {
  return {make_camera(Eigen::Matrix3d::Identity(), {0, 0, 0}), make_camera(rot_y(0.2), {1, 0, 0}),
          make_camera(rot_y(-0.2), {0, 1, 0})};
}

TEST(CandidatePool, EveryPairOnTheTieredGrid) {
  const GapsConfig c;  // step 0.125; tiers [0,1] ⊂ [-0.25,1.25] ⊂ [-0.5,1.5]
  const std::vector<Candidate> all = build_candidate_pool(three_cameras(), c);
  // α ∈ {-0.5, -0.375, ..., 1.5} is 17 values; without α = 0 and 1 (the cameras) 15, times 3 pairs.
  ASSERT_EQ(all.size(), 45u);
  int per_tier[3] = {0, 0, 0};
  for (const Candidate& cand : all) {
    EXPECT_NE(cand.alpha, 0.0);
    EXPECT_NE(cand.alpha, 1.0);
    EXPECT_DOUBLE_EQ(cand.d_extrap, extrapolation_distance(cand.alpha));
    EXPECT_LE(cand.d_extrap, c.max_extrap + 1e-12);
    EXPECT_EQ(cand.tier, alpha_tier(cand.alpha, c));
    EXPECT_FALSE(cand.admitted_before);
    ++per_tier[cand.tier];
  }
  EXPECT_EQ(per_tier[0], 3 * 7);  // 0.125 .. 0.875
  EXPECT_EQ(per_tier[1], 3 * 4);  // -0.25, -0.125, 1.125, 1.25
  EXPECT_EQ(per_tier[2], 3 * 4);  // -0.5, -0.375, 1.375, 1.5
  EXPECT_EQ(alpha_tier(-0.25, c), 1);
  EXPECT_EQ(alpha_tier(1.6, c), -1);
  // Pairs in lexicographic order, ids unique.
  std::set<int> ids;
  for (const Candidate& cand : all) {
    ids.insert(cand.id);
    const int expected_pair = cand.i == 0 ? cand.j - 1 : 2;
    EXPECT_EQ(cand.pair_index, expected_pair);
    EXPECT_LT(cand.i, cand.j);
  }
  EXPECT_EQ(ids.size(), all.size());
}

TEST(CandidatePool, LowerTiersAreSubsetsWithStableIds) {
  const GapsConfig c;
  const std::vector<Candidate> all = build_candidate_pool(three_cameras(), c);
  const std::vector<Candidate> tier0 = build_candidate_pool(three_cameras(), c, 0);
  ASSERT_EQ(tier0.size(), 21u);
  for (const Candidate& cand : tier0) {
    EXPECT_EQ(cand.tier, 0);
    EXPECT_EQ(cand.d_extrap, 0.0);
    const auto same = std::find_if(all.begin(), all.end(), [&](const Candidate& o) { return o.id == cand.id; });
    ASSERT_NE(same, all.end());
    EXPECT_EQ(same->pair_index, cand.pair_index);
    EXPECT_DOUBLE_EQ(same->alpha, cand.alpha);
  }
  // The candidate's camera is the interpolation of its pair.
  const Candidate& first = tier0.front();
  const Camera expected = interpolate_camera(three_cameras()[first.i], three_cameras()[first.j], first.alpha);
  expect_matrix_near(first.camera.R, expected.R, 1e-12);
  EXPECT_DOUBLE_EQ(first.alpha, 0.125);
}

TEST(CandidatePool, MaxExtrapCapsTheTiers) {
  GapsConfig c;
  c.max_extrap = 0.25;
  EXPECT_EQ(build_candidate_pool(three_cameras(), c).size(), 3u * 11);
}

// ---------------------------------------------------------------- the no-gaps ablation's static midpoints

// Nine cameras on a 3×3 grid of spacing 1 in the x-y plane, camera k at (k % 3, k / 3), all facing one way.
std::vector<Camera> nine_cameras() {
  std::vector<Camera> cams;
  for (int k = 0; k < 9; ++k) cams.push_back(make_camera(Eigen::Matrix3d::Identity(), {k % 3 * 1.0, k / 3 * 1.0, 0}));
  return cams;
}

using PairSet = std::set<std::pair<int, int>>;

TEST(StaticMidpoints, FewerPairsThanEightTakesThemAll) {
  const std::vector<std::pair<int, int>> pairs = spread_pairs(three_cameras(), kStaticMidpoints);
  ASSERT_EQ(pairs.size(), 3u);
  EXPECT_EQ(PairSet(pairs.begin(), pairs.end()), (PairSet{{0, 1}, {0, 2}, {1, 2}}));
}

TEST(StaticMidpoints, EightPairsSpreadOverNineCameras) {
  const std::vector<Camera> cams = nine_cameras();
  const std::vector<std::pair<int, int>> pairs = spread_pairs(cams, kStaticMidpoints);
  ASSERT_EQ(pairs.size(), 8u);
  EXPECT_EQ(PairSet(pairs.begin(), pairs.end()).size(), 8u);  // no pair twice
  std::vector<int> uses(9, 0);
  for (const auto& [i, j] : pairs) {
    EXPECT_LT(i, j);
    ++uses[i];
    ++uses[j];
    // Grid neighbours only: with every camera free, a pair at distance 1 is always available.
    EXPECT_NEAR(pose_distance(cams[i], cams[j]), 1.0, 1e-12) << i << "-" << j;
  }
  // 16 camera slots over 9 cameras: each serves once or twice; camera 0 is not in every pair.
  EXPECT_EQ(*std::min_element(uses.begin(), uses.end()), 1);
  EXPECT_EQ(*std::max_element(uses.begin(), uses.end()), 2);
  EXPECT_LT(uses[0], 8);
  // The first four pairs use eight distinct cameras: nobody serves twice before everyone served once.
  std::set<int> first_four;
  for (int k = 0; k < 4; ++k) first_four.insert({pairs[k].first, pairs[k].second});
  EXPECT_EQ(first_four.size(), 8u);
  // Deterministic: ties are broken by pair order.
  EXPECT_EQ(pairs, spread_pairs(cams, kStaticMidpoints));
  EXPECT_EQ(pairs.front(), (std::pair<int, int>{0, 1}));
}

TEST(StaticMidpoints, CandidatesAreThePairMidpoints) {
  const std::vector<Camera> cams = nine_cameras();
  const GapsConfig c;
  const std::vector<Candidate> mids = static_midpoints(cams, c);
  const std::vector<std::pair<int, int>> pairs = spread_pairs(cams, kStaticMidpoints, c.pose_rotation_weight);
  ASSERT_EQ(mids.size(), pairs.size());
  const std::vector<Candidate> pool = build_candidate_pool(cams, c, 0);
  std::set<int> ids;
  for (size_t k = 0; k < mids.size(); ++k) {
    const Candidate& m = mids[k];
    EXPECT_EQ(std::make_pair(m.i, m.j), pairs[k]);
    EXPECT_DOUBLE_EQ(m.alpha, 0.5);
    EXPECT_DOUBLE_EQ(m.d_extrap, 0.0);
    expect_vector_near(m.camera.center(), 0.5 * (cams[m.i].center() + cams[m.j].center()), 1e-12);
    // pair_index agrees with the pool's numbering of the same pair.
    const auto same =
        std::find_if(pool.begin(), pool.end(), [&](const Candidate& p) { return p.i == m.i && p.j == m.j; });
    ASSERT_NE(same, pool.end());
    EXPECT_EQ(m.pair_index, same->pair_index);
    ids.insert(m.id);
  }
  EXPECT_EQ(ids.size(), mids.size());
}

// ---------------------------------------------------------------- render statistics

at::Tensor grey_image(const at::Tensor& grey) { return grey.unsqueeze(2).repeat({1, 1, 3}); }

TEST(LocalEntropy, ConstantImageHasNone) {
  const at::Tensor image = at::full({5, 7, 3}, 0.42, kDouble);
  EXPECT_EQ(local_entropy_map(image, 16).abs().max().item<double>(), 0.0);
}

TEST(LocalEntropy, TwoLevelCheckerboard) {
  // 4×4 checkerboard of 0 and 1. Clipped windows: a corner sees 2×2 = 2+2 pixels and an edge 2×3 = 3+3,
  // both 1 bit; an interior 3×3 window sees 5 of one level and 4 of the other:
  // h9 = -(5/9 log2 5/9 + 4/9 log2 4/9) = 0.99107606 bits. With 16 bins the map is divided by log2 9.
  const at::Tensor board = (at::arange(4, kDouble).view({4, 1}) + at::arange(4, kDouble).view({1, 4})).remainder(2);
  const double h9 = -(5.0 / 9 * std::log2(5.0 / 9) + 4.0 / 9 * std::log2(4.0 / 9));
  EXPECT_NEAR(h9, 0.99107606, 1e-8);
  const double log2_9 = 3.169925001442312;

  const at::Tensor h = local_entropy_map(grey_image(board), 16);
  EXPECT_NEAR(h[0][0].item<double>(), 1.0 / log2_9, 1e-9);  // corner
  EXPECT_NEAR(h[0][2].item<double>(), 1.0 / log2_9, 1e-9);  // edge
  EXPECT_NEAR(h[1][1].item<double>(), h9 / log2_9, 1e-9);   // interior
  EXPECT_NEAR(h[2][1].item<double>(), h9 / log2_9, 1e-9);
  EXPECT_NEAR(h.mean().item<double>(), (12 * 1.0 + 4 * h9) / 16 / log2_9, 1e-9);
  // With 2 bins the most a window can hold is 1 bit, so the map is in bits.
  const at::Tensor h2 = local_entropy_map(grey_image(board), 2);
  EXPECT_NEAR(h2[0][0].item<double>(), 1.0, 1e-9);
  EXPECT_NEAR(h2[1][2].item<double>(), h9, 1e-9);
}

TEST(RenderStats, CoverageAndContrast) {
  const at::Tensor alpha = at::tensor({0.2, 0.5, 0.7, 1.0}, kDouble).view({2, 2});
  EXPECT_DOUBLE_EQ(coverage_fraction(alpha, 0.5), 0.75);
  // Half black, half white: luma std = 0.5.
  const at::Tensor half = at::tensor({0.0, 1.0, 0.0, 1.0}, kDouble).view({2, 2});
  EXPECT_NEAR(rms_contrast(grey_image(half)), 0.5, 1e-12);
  EXPECT_NEAR(rms_contrast(at::full({3, 3, 3}, 0.3, kDouble)), 0.0, 1e-12);
  // Luma weights sum to 1, so grey stays grey.
  const at::Tensor g = greyscale(at::full({1, 1, 3}, 0.6, kDouble));
  EXPECT_NEAR(g.item<double>(), 0.6, 1e-12);

  const GapsConfig c;
  const CandidateMeasurements m = measure_render(grey_image(half), alpha, 0.4, 0.7, 0.1, c);
  EXPECT_NEAR(m.mean_alpha, 0.6, 1e-12);
  EXPECT_DOUBLE_EQ(m.coverage, 0.75);
  EXPECT_NEAR(m.contrast, 0.5, 1e-12);
  EXPECT_NEAR(m.entropy_mean, 1.0 / 3.169925001442312, 1e-9);  // every clipped window of a 2×2 board: 1 bit
  EXPECT_DOUBLE_EQ(m.d_min_supervised, 0.4);
  EXPECT_DOUBLE_EQ(m.d_min_gt, 0.7);
  EXPECT_DOUBLE_EQ(*m.uncertainty_variance_history, 0.1);
}

// ---------------------------------------------------------------- score terms

CandidateMeasurements example_measurements() {
  CandidateMeasurements m;
  m.mean_alpha = 0.4;
  m.entropy_mean = 0.5;
  m.coverage = 0.6;
  m.contrast = 0.125;
  m.d_min_supervised = 0.25;
  m.d_min_gt = 0.0;
  m.uncertainty_variance_history = 0.15;
  return m;
}

TEST(GapsScore, Novelty) {
  const GapsConfig c;
  EXPECT_DOUBLE_EQ(novelty(0.0, c), 0.0);
  EXPECT_DOUBLE_EQ(novelty(0.25, c), 0.8);       // 4 · 0.25 / 1.25
  EXPECT_DOUBLE_EQ(novelty(1.0 / 3.0, c), 1.0);  // saturates at d = 1/3
  EXPECT_DOUBLE_EQ(novelty(2.0, c), 1.0);
}

TEST(GapsScore, ReconInformativeness) {
  const GapsConfig c;
  // 0.2 (1 - 0.4) + 0.2 · 0.5 + 0.6 · 0.8 = 0.12 + 0.10 + 0.48.
  EXPECT_NEAR(recon_informativeness(example_measurements(), c), 0.70, 1e-12);
}

TEST(GapsScore, ConfidenceTerms) {
  const GapsConfig c;
  const CandidateMeasurements m = example_measurements();
  // C_init = 0.5 · 0.6 + 0.5 · min(1, 0.125 / 0.25) = 0.55.
  EXPECT_NEAR(initial_confidence(m, c), 0.55, 1e-12);
  EXPECT_DOUBLE_EQ(reference_confidence(0.0, c), 1.0);
  EXPECT_NEAR(reference_confidence(0.5, c), std::exp(-1.0), 1e-12);
  EXPECT_NEAR(reference_confidence(1.0, c), std::exp(-2.0), 1e-12);
  // C_model = 0.5 · 0.55 + 0.5 · 1.
  EXPECT_NEAR(model_confidence(m, c), 0.775, 1e-12);
  EXPECT_NEAR(history_confidence(0.15, c), 0.5, 1e-12);
  EXPECT_DOUBLE_EQ(history_confidence(0.0, c), 1.0);
  EXPECT_DOUBLE_EQ(history_confidence(0.6, c), 0.0);  // clipped at 0
  // C_gen = 0.3 · 0.775 + 0.7 · 0.5.
  EXPECT_NEAR(generative_confidence(m, c), 0.5825, 1e-12);
  CandidateMeasurements fresh = m;
  fresh.uncertainty_variance_history.reset();
  EXPECT_NEAR(generative_confidence(fresh, c), 0.775, 1e-12);  // no history: C_model alone
  // Contrast above the reference saturates.
  fresh.contrast = 0.5;
  EXPECT_NEAR(initial_confidence(fresh, c), 0.8, 1e-12);
}

TEST(GapsScore, HistoryIsTheMeanOverEveryPhaseThatGeneratedTheView) {
  UncertaintyHistory history;
  EXPECT_FALSE(mean_uncertainty_variance(history, 3).has_value());
  history[3] = {0.1};
  EXPECT_DOUBLE_EQ(*mean_uncertainty_variance(history, 3), 0.1);
  history[3].push_back(0.3);
  EXPECT_DOUBLE_EQ(*mean_uncertainty_variance(history, 3), 0.2);  // (0.1 + 0.3) / 2, not the last
  EXPECT_FALSE(mean_uncertainty_variance(history, 4).has_value());
}

TEST(GapsScore, AHighVarianceGenerationLowersTheNextConfidence) {
  // A view generated once with variance 0.27 (rejected or not: the history does not ask) scores C_hist =
  // 1 - 0.27 / 0.3 = 0.1 next phase, well below its C_model of 0.775.
  const GapsConfig c;
  CandidateMeasurements m = example_measurements();
  m.uncertainty_variance_history.reset();
  const double before = generative_confidence(m, c);
  UncertaintyHistory history = {{5, {0.27}}};
  m.uncertainty_variance_history = mean_uncertainty_variance(history, 5);
  EXPECT_NEAR(generative_confidence(m, c), 0.3 * 0.775 + 0.7 * 0.1, 1e-12);
  EXPECT_LT(generative_confidence(m, c), before);
  // A second, good generation (variance 0.03) brings the mean to 0.15 and C_hist to 0.5.
  history[5].push_back(0.03);
  m.uncertainty_variance_history = mean_uncertainty_variance(history, 5);
  EXPECT_NEAR(generative_confidence(m, c), 0.3 * 0.775 + 0.7 * 0.5, 1e-12);
}

TEST(GapsScore, BetaAnnealsLinearly) {
  const GapsConfig c;  // β 2.0 -> 0.5
  EXPECT_DOUBLE_EQ(annealed_beta(0, 10000, c), 2.0);
  EXPECT_DOUBLE_EQ(annealed_beta(5000, 10000, c), 1.25);
  EXPECT_DOUBLE_EQ(annealed_beta(10000, 10000, c), 0.5);
  EXPECT_DOUBLE_EQ(annealed_beta(12000, 10000, c), 0.5);
}

TEST(GapsScore, ScoreIsReconTimesConfidenceToBeta) {
  const GapsConfig c;
  const ScoreTerms s = score_candidate(example_measurements(), 5000, 10000, c);
  EXPECT_NEAR(s.i_recon, 0.70, 1e-12);
  EXPECT_NEAR(s.c_model, 0.775, 1e-12);
  EXPECT_NEAR(s.c_gen, 0.5825, 1e-12);
  EXPECT_DOUBLE_EQ(s.beta, 1.25);
  EXPECT_NEAR(s.score, 0.70 * std::pow(0.5825, 1.25), 1e-12);
  // Early (β = 2) the same view scores lower than late (β = 0.5): confidence weighs more.
  EXPECT_NEAR(score_candidate(example_measurements(), 0, 10000, c).score, 0.70 * 0.5825 * 0.5825, 1e-12);
  EXPECT_NEAR(score_candidate(example_measurements(), 10000, 10000, c).score, 0.70 * std::sqrt(0.5825), 1e-12);
}

// ---------------------------------------------------------------- selection

Candidate candidate_at(double x, int pair_index, bool admitted_before = false, double yaw = 0.0) {
  Candidate cand;
  cand.camera = make_camera(rot_y(yaw), {x, 0, 0});
  cand.pair_index = pair_index;
  cand.admitted_before = admitted_before;
  return cand;
}

TEST(GapsSelection, GreedyRespectsDiversityAndPairCap) {
  GapsConfig c;
  c.n_active = 4;  // two pairs -> cap ceil(4 / 2) = 2
  // Pool positions shuffled against score order 1, 3, 5, 4, 0, 6, 2.
  const std::vector<Candidate> pool = {candidate_at(3.0, 1), candidate_at(0.0, 0), candidate_at(5.0, 1),
                                       candidate_at(0.1, 1), candidate_at(2.0, 0), candidate_at(1.0, 0),
                                       candidate_at(4.0, 1)};
  const std::vector<double> scores = {0.5, 0.9, 0.3, 0.8, 0.6, 0.7, 0.4};
  // 1 taken; 3 is 0.1 < 0.15 from 1; 5 taken (pair 0 now full); 4 over the cap; 0 and 6 taken.
  EXPECT_EQ(select_greedy(pool, scores, c), (std::vector<int>{1, 5, 0, 6}));

  // Larger budget: the cap becomes ceil(6 / 2) = 3, so 4 returns; 3 stays excluded by diversity.
  c.n_active = 6;
  EXPECT_EQ(select_greedy(pool, scores, c), (std::vector<int>{1, 5, 4, 0, 6, 2}));
}

TEST(GapsSelection, DiversityCountsRotation) {
  GapsConfig c;
  c.n_active = 3;
  // Same centre: 0.4 rad -> distance 0.2 (kept apart); 0.2 rad -> 0.1 (too close).
  const std::vector<Candidate> pool = {candidate_at(0, 0), candidate_at(0, 1, false, 0.2),
                                       candidate_at(0, 2, false, 0.4)};
  EXPECT_EQ(select_greedy(pool, {0.9, 0.8, 0.7}, c), (std::vector<int>{0, 2}));
}

TEST(GapsSelection, ForcedExplorationReplacesTheCeilingOfAQuarter) {
  const GapsConfig c;
  std::vector<Candidate> pool;
  for (int k = 0; k < 5; ++k) pool.push_back(candidate_at(k, k, /*admitted_before=*/true));
  pool.push_back(candidate_at(0.05, 5));  // never admitted but within 0.15 of kept view 0
  pool.push_back(candidate_at(6, 6));
  pool.push_back(candidate_at(7, 7));
  pool.push_back(candidate_at(8, 8));
  pool.push_back(candidate_at(9, 9, true));
  const std::vector<double> scores = {0.9, 0.8, 0.7, 0.6, 0.5, 0.45, 0.4, 0.35, 0.3, 0.2};
  const std::vector<int> selected = {0, 1, 2, 3, 4};
  // ceil(0.25 · 5) = 2: the two lowest (3, 4) go; 5 is too close to 0, so 6 and 7 come in.
  const std::vector<int> out = force_exploration(pool, scores, selected, c);
  EXPECT_EQ(out, (std::vector<int>{0, 1, 2, 6, 7}));
  int fresh = 0;
  for (int k : out) fresh += pool[k].admitted_before ? 0 : 1;
  EXPECT_EQ(fresh, 2);
  // ceil(0.25 · 4) = 1 exactly.
  EXPECT_EQ(force_exploration(pool, scores, {0, 1, 2, 3}, c), (std::vector<int>{0, 1, 2, 6}));
}

TEST(GapsSelection, ForcedExplorationKeepsTheBatchWhenThePoolRunsOut) {
  const GapsConfig c;
  std::vector<Candidate> pool;
  for (int k = 0; k < 5; ++k) pool.push_back(candidate_at(k, k, true));
  pool.push_back(candidate_at(6, 5));  // the only never-admitted candidate
  const std::vector<double> scores = {0.9, 0.8, 0.7, 0.6, 0.5, 0.1};
  EXPECT_EQ(force_exploration(pool, scores, {0, 1, 2, 3, 4}, c), (std::vector<int>{0, 1, 2, 5, 3}));
}

TEST(GapsSelection, ExplorationEveryThirdPhase) {
  const GapsConfig c;
  EXPECT_FALSE(is_exploration_phase(0, c));
  EXPECT_FALSE(is_exploration_phase(1, c));
  EXPECT_TRUE(is_exploration_phase(2, c));
  EXPECT_FALSE(is_exploration_phase(3, c));
  EXPECT_TRUE(is_exploration_phase(5, c));

  GapsConfig small = c;
  small.n_active = 4;
  std::vector<Candidate> pool;
  for (int k = 0; k < 4; ++k) pool.push_back(candidate_at(k, k, true));
  pool.push_back(candidate_at(10, 4));
  const std::vector<double> scores = {0.9, 0.8, 0.7, 0.6, 0.1};
  EXPECT_EQ(select_for_phase(pool, scores, 1, small), (std::vector<int>{0, 1, 2, 3}));
  EXPECT_EQ(select_for_phase(pool, scores, 2, small), (std::vector<int>{0, 1, 2, 4}));
}

TEST(GapsTiers, UpgradeWhenAdmittedViewsAreCertain) {
  const GapsConfig c;                             // threshold 0.01, three tiers
  EXPECT_EQ(next_tier(0, {0.002, 0.006}, c), 1);  // mean 0.004 < 0.01
  EXPECT_EQ(next_tier(1, {0.008}, c), 2);
  EXPECT_EQ(next_tier(0, {0.008, 0.016}, c), 0);  // mean 0.012
  EXPECT_EQ(next_tier(0, {}, c), 0);              // nothing admitted: no evidence
  EXPECT_EQ(next_tier(2, {0.0}, c), 2);           // already the widest
  GapsConfig strict = c;
  strict.tier_min_admitted = 3;
  EXPECT_EQ(next_tier(0, {0.001, 0.001}, strict), 0);
  EXPECT_EQ(next_tier(0, {0.001, 0.001, 0.001}, strict), 1);
}

}  // namespace
}  // namespace gaps

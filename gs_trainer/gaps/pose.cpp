#include "gs_trainer/gaps/pose.h"

#include <algorithm>
#include <cmath>
#include <limits>
#include <tuple>
#include <utility>

#include <absl/strings/str_format.h>
#include <Eigen/Geometry>

namespace gaps {

namespace {

// Grid positions closer than this are treated as equal (α = k * step is not exact in binary).
constexpr double kAlphaEps = 1e-9;

// Geodesic angle between two rotations, in [0, π].
double rotation_angle(const Eigen::Matrix3d& a, const Eigen::Matrix3d& b) {
  return Eigen::AngleAxisd(a.transpose() * b).angle();
}

double lerp(double x, double y, double alpha) { return (1.0 - alpha) * x + alpha * y; }

// eq:slerp rotation: R_a (R_aᵀ R_b)^α, the power scaling the relative rotation's angle.
Eigen::Matrix3d slerp_rotation(const Eigen::Matrix3d& ra, const Eigen::Matrix3d& rb, double alpha) {
  const Eigen::AngleAxisd rel(ra.transpose() * rb);
  return ra * Eigen::AngleAxisd(alpha * rel.angle(), rel.axis()).toRotationMatrix();
}

void set_intrinsics(Camera& out, const Camera& a, const Camera& b, double alpha, bool interpolate) {
  if (!interpolate) return;  // `out` already carries a's intrinsics
  const Camera bs = (b.width == a.width && b.height == a.height) ? b : b.resized(a.width, a.height);
  out.fx = lerp(a.fx, bs.fx, alpha);
  out.fy = lerp(a.fy, bs.fy, alpha);
  out.cx = lerp(a.cx, bs.cx, alpha);
  out.cy = lerp(a.cy, bs.cy, alpha);
}

bool is_training_pose(double alpha) { return std::abs(alpha) < kAlphaEps || std::abs(alpha - 1.0) < kAlphaEps; }

}  // namespace

double pose_distance(const Camera& a, const Camera& b, double rotation_weight) {
  return (a.center() - b.center()).norm() + rotation_weight * rotation_angle(a.R, b.R);
}

double min_pose_distance(const Camera& view, const std::vector<Camera>& others, double rotation_weight) {
  double best = std::numeric_limits<double>::infinity();
  for (const Camera& o : others) best = std::min(best, pose_distance(view, o, rotation_weight));
  return best;
}

double extrapolation_distance(double alpha) { return std::max(0.0, -alpha) + std::max(0.0, alpha - 1.0); }

Camera interpolate_camera(const Camera& a, const Camera& b, double alpha, bool interpolate_intrinsics) {
  Camera out = a;
  out.name = absl::StrFormat("pseudo_%s_%s_a%+.4f", a.name, b.name, alpha);
  out.image_path.clear();
  out.distortion.clear();
  out.R = slerp_rotation(a.R, b.R, alpha);
  const Eigen::Vector3d centre = (1.0 - alpha) * a.center() + alpha * b.center();
  out.t = -out.R * centre;
  out.near = lerp(a.near, b.near, alpha);
  out.far = lerp(a.far, b.far, alpha);
  set_intrinsics(out, a, b, alpha, interpolate_intrinsics);
  return out;
}

int alpha_tier(double alpha, const GapsConfig& c) {
  for (int k = 0; k < c.num_tiers(); ++k) {
    if (alpha >= c.tier_alpha_min[k] - kAlphaEps && alpha <= c.tier_alpha_max[k] + kAlphaEps) return k;
  }
  return -1;
}

namespace {

// The α values of the full (all-tier) grid: multiples of alpha_step inside some tier, within max_extrap,
// without the training poses α = 0 and 1. It depends on the config only, so ids built on it are stable.
std::vector<double> alpha_grid(const GapsConfig& c) {
  const double lo = *std::min_element(c.tier_alpha_min.begin(), c.tier_alpha_min.end());
  const double hi = *std::max_element(c.tier_alpha_max.begin(), c.tier_alpha_max.end());
  const int k_lo = static_cast<int>(std::ceil(lo / c.alpha_step - kAlphaEps));
  const int k_hi = static_cast<int>(std::floor(hi / c.alpha_step + kAlphaEps));
  std::vector<double> grid;
  for (int k = k_lo; k <= k_hi; ++k) {
    const double alpha = k * c.alpha_step;
    if (is_training_pose(alpha) || alpha_tier(alpha, c) < 0) continue;
    if (extrapolation_distance(alpha) > c.max_extrap + kAlphaEps) continue;
    grid.push_back(alpha);
  }
  return grid;
}

Candidate make_candidate(const std::vector<Camera>& cameras, int i, int j, double alpha, const GapsConfig& c) {
  Candidate cand;
  cand.camera = interpolate_camera(cameras[i], cameras[j], alpha, c.interpolate_intrinsics);
  cand.i = i;
  cand.j = j;
  cand.alpha = alpha;
  cand.d_extrap = extrapolation_distance(alpha);
  cand.tier = alpha_tier(alpha, c);
  return cand;
}

}  // namespace

std::vector<Candidate> build_candidate_pool(const std::vector<Camera>& cameras, const GapsConfig& c, int max_tier) {
  if (max_tier < 0) max_tier = c.num_tiers() - 1;
  const std::vector<double> grid = alpha_grid(c);
  std::vector<Candidate> pool;
  int pair_index = 0;
  for (int i = 0; i < static_cast<int>(cameras.size()); ++i) {
    for (int j = i + 1; j < static_cast<int>(cameras.size()); ++j, ++pair_index) {
      for (size_t g = 0; g < grid.size(); ++g) {
        if (alpha_tier(grid[g], c) > max_tier) continue;
        Candidate cand = make_candidate(cameras, i, j, grid[g], c);
        cand.pair_index = pair_index;
        cand.id = pair_index * static_cast<int>(grid.size()) + static_cast<int>(g);
        pool.push_back(std::move(cand));
      }
    }
  }
  return pool;
}

namespace {

// Index of the pair (i, j), i < j, among the pairs of n cameras in lexicographic order (build_candidate_pool's).
int pair_index_of(int i, int j, int n) { return i * (2 * n - i - 1) / 2 + (j - i - 1); }

}  // namespace

std::vector<std::pair<int, int>> spread_pairs(const std::vector<Camera>& cameras, int count, double rotation_weight) {
  const int n = static_cast<int>(cameras.size());
  std::vector<std::pair<int, int>> left;
  for (int i = 0; i < n; ++i)
    for (int j = i + 1; j < n; ++j) left.emplace_back(i, j);
  std::vector<int> uses(n, 0);
  std::vector<std::pair<int, int>> chosen;
  while (static_cast<int>(chosen.size()) < count && !left.empty()) {
    // Lexicographic comparison of (busiest camera, total use, distance); `left` stays in pair order, so the
    // first of equal keys has the lower pair index.
    const auto key = [&](const std::pair<int, int>& p) {
      const auto [i, j] = p;
      return std::make_tuple(std::max(uses[i], uses[j]), uses[i] + uses[j],
                             pose_distance(cameras[i], cameras[j], rotation_weight));
    };
    const auto best =
        std::min_element(left.begin(), left.end(), [&](const auto& a, const auto& b) { return key(a) < key(b); });
    ++uses[best->first];
    ++uses[best->second];
    chosen.push_back(*best);
    left.erase(best);
  }
  return chosen;
}

std::vector<Candidate> static_midpoints(const std::vector<Camera>& cameras, const GapsConfig& c, int count) {
  std::vector<Candidate> out;
  for (const auto& [i, j] : spread_pairs(cameras, count, c.pose_rotation_weight)) {
    Candidate cand = make_candidate(cameras, i, j, 0.5, c);
    cand.pair_index = pair_index_of(i, j, static_cast<int>(cameras.size()));
    cand.id = cand.pair_index;
    out.push_back(std::move(cand));
  }
  return out;
}

}  // namespace gaps

#pragma once
// Pose maths of Generative Active Pseudo-view Selection (paper sec. 3.4): the pose distance
// (eq:pose_dist), geodesic interpolation/extrapolation between two cameras (eq:slerp) and the candidate
// pool built from every training pair with progressive α tiers.
#include <utility>
#include <vector>

#include "gs_trainer/gaps/config.h"
#include "gs_trainer/scene/camera.h"

namespace gaps {

// eq:pose_dist: d = ||c1 - c2|| + w * θ, θ = arccos((tr(R1ᵀR2) - 1) / 2) the geodesic rotation angle.
// Translation is measured between camera centres, not the world-to-camera t of the paper's notation:
// t = -R c mixes in the rotation, so two cameras at one place would otherwise be "apart" when turned.
// θ is taken from the angle-axis of R1ᵀR2, which equals the arccos form but stays accurate near 0.
double pose_distance(const Camera& a, const Camera& b, double rotation_weight = 0.5);

// Smallest pose distance from `view` to any of `others` (+infinity when empty).
double min_pose_distance(const Camera& view, const std::vector<Camera>& others, double rotation_weight = 0.5);

// d_extrap = max(0, -α) + max(0, α - 1) (sec. 3.4): 0 between the cameras, growing beyond them.
double extrapolation_distance(double alpha);

// The camera at α along the geodesic from a (α = 0) to b (α = 1); α outside [0, 1] extrapolates.
// eq:slerp: R(α) = R_a (R_aᵀ R_b)^α with the power taken on the angle-axis (so it extrapolates too), and
// the centre lerped, c(α) = (1 - α) c_a + α c_b (brief: lerp of the centre; t(α) = -R(α) c(α)).
// Image size is a's; intrinsics are lerped after rescaling b's to a's size (or copied from a when
// interpolate_intrinsics is false); near/far are lerped; no distortion (pseudo-views are rendered).
Camera interpolate_camera(const Camera& a, const Camera& b, double alpha, bool interpolate_intrinsics = true);

// One candidate pseudo-view pose of the pool.
struct Candidate {
  Camera camera;
  int id = -1;                   // stable: the index on the full (last-tier) grid, whatever max_tier was used
  int pair_index = -1;           // index of the pair (i, j), i < j, in lexicographic order
  int i = -1, j = -1;            // training-camera indices of the pair
  double alpha = 0;              // position along the pair's geodesic (eq:slerp)
  double d_extrap = 0;           // extrapolation_distance(alpha)
  int tier = 0;                  // smallest tier whose α range contains alpha
  bool admitted_before = false;  // set by the caller once a pseudo-view at this pose was admitted
};

// Smallest tier k with tier_alpha_min[k] <= α <= tier_alpha_max[k], or -1 when none contains α.
int alpha_tier(double alpha, const GapsConfig& c);

// Candidates for every pair of `cameras` on the grid α = k * alpha_step within the tiers up to max_tier
// (-1: all), with d_extrap <= max_extrap. α = 0 and α = 1 are left out: they are the training cameras.
// Order: pair-major, α ascending; ids index the full grid so they agree between calls.
std::vector<Candidate> build_candidate_pool(const std::vector<Camera>& cameras, const GapsConfig& c, int max_tier = -1);

// Pseudo-views of the no-gaps ablation (paper sec. ablation).
inline constexpr int kStaticMidpoints = 8;

// `count` training pairs (i < j), every pair when there are no more: picked one at a time, each time the pair
// whose cameras have served least so far (the larger of their two counts, then their sum), the shorter
// pose distance (eq:pose_dist) between equally used ones, then the lower pair index. Returned in that order.
// Why: the paper fixes eight midpoints but not their pairs. Lexicographic order would route all eight through
// camera 0 from 9 cameras on, so the static set would supervise one corner of the capture; spreading the
// cameras covers it as evenly as eight views can. Among equally spread choices, nearby pairs see the same
// content, so their midpoints are the interpolations a fixed-pose baseline can ground best.
std::vector<std::pair<int, int>> spread_pairs(const std::vector<Camera>& cameras, int count,
                                              double rotation_weight = 0.5);

// The no-gaps ablation's static set: the midpoints (α = 0.5) of spread_pairs(cameras, count). They are not
// drawn from the pool (α = 0.5 need not lie on its grid), so their ids are the pair indices.
std::vector<Candidate> static_midpoints(const std::vector<Camera>& cameras, const GapsConfig& c,
                                        int count = kStaticMidpoints);

}  // namespace gaps

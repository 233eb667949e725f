#pragma once
// Sparse point cloud from the N training views with their known poses (no pose estimation): SIFT on each
// image, exhaustive pairwise matching (Lowe ratio + mutual best), rejection of matches that break the
// epipolar geometry of the given poses, tracks by union-find, multi-view DLT + Gauss-Newton triangulation,
// and reprojection / triangulation-angle / cheirality filters. The role of COLMAP's feature_extractor,
// exhaustive_matcher and point_triangulator in the paper's initialisation.
#include <optional>
#include <utility>
#include <vector>

#include <ATen/Tensor.h>
#include <Eigen/Core>
#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "gs_trainer/scene/camera.h"
#include "gs_trainer/scene/scene.h"

namespace gaps {

struct SparseOptions {
  int max_features = 6000;           // SIFT keypoints per image (strongest first)
  double contrast_threshold = 0.01;  // SIFT's; a quarter of OpenCV's default: the images are small (-r 8)
  double ratio = 0.8;                // Lowe's ratio test on descriptor distances
  // Largest descriptor distance accepted, as the angle (radians) between unit descriptors (COLMAP's 0.7).
  double max_descriptor_angle = 0.7;
  // Guided matching: the poses are known, so each keypoint's nearest-neighbour and ratio test only consider
  // keypoints within max_epipolar_px of its epipolar line (COLMAP's guided_matching). Between far-apart
  // sparse views this roughly doubles the triangulated points (fern 3 views: 322 -> 563, bonsai 12 views:
  // 699 -> 1434) at a median reprojection error still ~0.2-0.3 px. Off: plain exhaustive matching, with the
  // epipolar test applied afterwards (COLMAP's default).
  bool guided_matching = true;
  double max_epipolar_px = 2.0;      // point-to-epipolar-line distance, both directions
  double max_reprojection_px = 2.0;  // every kept observation of a point
  double min_angle_deg = 1.5;        // largest angle between two observing rays
  int refine_iterations = 5;         // Gauss-Newton steps after the DLT
  // > 0: SIFT and triangulation work on the views brought down to this longest side (the points stay in world
  // units), so that PatchMatch can read larger views (--init-resolution) without SIFT's matching growing with
  // them: fern 9 views' SIFT takes 30.7 s at -r 4 against 1.4 s at -r 8 on two cores. 0: the views as given.
  int max_image_side = 0;
};

// One 2D observation of a track: a view index and a pixel position in camera.h's convention (pixel (i, j)
// has its centre at (i + 0.5, j + 0.5)).
struct Observation {
  int view = 0;
  Eigen::Vector2d xy = Eigen::Vector2d::Zero();
};

// A keypoint match between two views, by keypoint index.
struct Match {
  int a = 0;
  int b = 0;
};

// Keypoints of one image, positions in camera.h's pixel convention, descriptors as an Nx128 float tensor
// of unit rows.
struct Features {
  std::vector<Eigen::Vector2d> xy;
  at::Tensor descriptors;
};

struct SparseStats {
  int64_t keypoints = 0;         // over all views
  int64_t ratio_matches = 0;     // over all pairs: mutual best + ratio test (among epipolar candidates if guided)
  int64_t epipolar_matches = 0;  // of those, consistent with the known poses
  int degenerate_pairs = 0;      // pairs with (almost) no baseline: no epipolar geometry, skipped
  int64_t tracks = 0;            // union-find components seen in >= 2 views
  int64_t rejected_cheirality = 0;
  int64_t rejected_reprojection = 0;
  int64_t rejected_angle = 0;
  int64_t points = 0;
  double median_reprojection_px = 0.0;  // over every observation of the kept points
  double seconds = 0.0;
};

struct SparseResult {
  PointCloud points;                          // xyz and the mean observed colour
  std::vector<std::vector<int>> point_views;  // views observing each point (for neighbour selection)
  SparseStats stats;
};

// InvalidArgument naming the first option out of range (max_image_side: 0, or at least kMinSparseImageSide).
inline constexpr int kMinSparseImageSide = 32;
absl::Status validate_sparse_options(const SparseOptions& options);

// One HxWx3 image per camera, at the camera's size; the error names the first view that is not.
absl::Status check_view_images(const std::vector<Camera>& cameras, const std::vector<at::Tensor>& images);

// Projection of a world point to pixels; nullopt when it is not in front of the camera (z <= 0).
std::optional<Eigen::Vector2d> project_point(const Camera& camera, const Eigen::Vector3d& xyz);

// F with x_b^T F x_a = 0 for homogeneous pixel positions, from the known poses and intrinsics. Zero (up to
// rounding) when the two centres coincide.
Eigen::Matrix3d fundamental_matrix(const Camera& a, const Camera& b);
// Larger of the two point-to-epipolar-line distances (px): x_b to F x_a, and x_a to F^T x_b.
double epipolar_distance(const Eigen::Matrix3d& F, const Eigen::Vector2d& xa, const Eigen::Vector2d& xb);
// The matches whose epipolar distance is below max_px.
std::vector<Match> epipolar_filter(const Camera& ca, const Camera& cb, const std::vector<Eigen::Vector2d>& xa,
                                   const std::vector<Eigen::Vector2d>& xb, const std::vector<Match>& matches,
                                   double max_px);

// SIFT on the grey image (HxWx3 float in [0, 1], any device).
Features detect_features(const at::Tensor& image, const SparseOptions& options);
// Mutual nearest neighbours passing Lowe's ratio test in both directions and the descriptor distance limit.
// With `F` (x_b^T F x_a = 0), only pairs within band_px of each other's epipolar lines are candidates.
std::vector<Match> match_features(const Features& a, const Features& b, const SparseOptions& options,
                                  const Eigen::Matrix3d* F = nullptr);

// Connected components of the match graph over (view, keypoint) nodes. A component with two keypoints in
// one view is ambiguous there, so that view's observations are dropped; components left with fewer than
// two views are discarded. matches[i][j] (i < j) holds the matches of views i and j.
std::vector<std::vector<std::pair<int, int>>> build_tracks(const std::vector<int>& keypoints_per_view,
                                                           const std::vector<std::vector<std::vector<Match>>>& matches);

// Linear triangulation (DLT in normalised image coordinates) of >= 2 observations; the point may be at
// infinity or behind a camera: the caller checks.
Eigen::Vector3d triangulate_dlt(const std::vector<Camera>& cameras, const std::vector<Observation>& observations);
// Gauss-Newton on the summed squared reprojection error (px), at most `iterations` accepted steps.
Eigen::Vector3d refine_point(const std::vector<Camera>& cameras, const std::vector<Observation>& observations,
                             const Eigen::Vector3d& xyz, int iterations);
// Largest angle (degrees) between the rays from the observing camera centres to the point.
double triangulation_angle_deg(const std::vector<Camera>& cameras, const std::vector<Observation>& observations,
                               const Eigen::Vector3d& xyz);

enum class TrackVerdict { kKept, kCheirality, kReprojection, kAngle };

struct TriangulatedPoint {
  Eigen::Vector3d xyz = Eigen::Vector3d::Zero();
  std::vector<Observation> observations;  // the ones kept (outliers of long tracks are dropped)
  std::vector<double> errors_px;          // reprojection error of each kept observation
};

// DLT + refinement + filters. Observations over the reprojection limit are dropped one by one (worst first)
// while more than two remain, so one bad match does not cost a long track.
TrackVerdict triangulate_track(const std::vector<Camera>& cameras, std::vector<Observation> observations,
                               const SparseOptions& options, TriangulatedPoint* out);

// The whole sparse stage. cameras[i] must have the size of images[i] (HxWx3 float in [0, 1]). Fails only
// on invalid input; too few views or matches give an empty cloud with the stats saying why.
absl::StatusOr<SparseResult> sparse_reconstruct(const std::vector<Camera>& cameras,
                                                const std::vector<at::Tensor>& images,
                                                const SparseOptions& options = {});

}  // namespace gaps

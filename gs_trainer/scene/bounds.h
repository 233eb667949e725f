#pragma once
// How large a scene is, seen from its cameras: the extent of the camera centres, a far bound where the
// format gives none, and random points inside the viewing frusta (the `random` initialisation).
#include <cstdint>
#include <optional>
#include <vector>

#include "common/point_cloud.h"
#include "gs_trainer/scene/camera.h"

namespace gaps {

// Uniform random points inside the cameras' viewing frusta between each camera's near and far bounds
// (or between 0.1 and `fallback_far` when the scene gives none), with random colours.
PointCloud random_points_in_views(const std::vector<Camera>& cameras, int64_t count, double fallback_far,
                                  uint64_t seed);

// The point the cameras' optical axes pass closest to (least squares), when there are two or more cameras,
// the axes are not (nearly) parallel and the point lies in front of every camera: what a capture looks at.
std::optional<Eigen::Vector3d> optical_axes_target(const std::vector<Camera>& cameras);

// A far bound for scenes whose format gives none: twice the distance from the cameras to the point their
// optical axes pass closest to (what a capture looks at), or 2 * cameras_extent + 1 when the axes do not
// converge in front of the cameras (e.g. parallel).
double default_far_bound(const std::vector<Camera>& cameras);

// Radius of the sphere around the camera centres, x1.1 (3DGS's "cameras extent"); scales learning rates
// and densification thresholds.
double cameras_extent(const std::vector<Camera>& cameras);

}  // namespace gaps

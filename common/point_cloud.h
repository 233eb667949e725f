#pragma once
// A coloured point cloud: what initialisations make, scenes ship and PLY files hold.
#include <string>

#include <ATen/Tensor.h>
#include "absl/status/status.h"

namespace gaps {

struct PointCloud {
  at::Tensor xyz;  // N x 3 float32
  at::Tensor rgb;  // N x 3 float32 in [0, 1]
};

// The largest coordinate a scene may hold. Training runs in float32, where distances are squared: values
// finite as doubles but beyond this (1e30, or 1e300 that becomes inf as a float) overflow there and poison
// everything downstream, so they are refused where they enter.
inline constexpr double kMaxCoordinate = 1e15;

// OK when xyz is N x 3 and every coordinate is finite and within kMaxCoordinate; `where` names the source.
absl::Status check_point_cloud(const PointCloud& points, const std::string& where);

}  // namespace gaps

#pragma once
// The host-side conversions into patchmatch_math.h's plain float types (which the CUDA kernels share, so
// they know nothing of Camera or Eigen).
#include <Eigen/Core>

#include "gs_trainer/init/patchmatch_math.h"
#include "gs_trainer/scene/camera.h"

namespace gaps::pm {

inline ViewGeometry view_geometry(const Camera& c) {
  return {static_cast<float>(c.fx),
          static_cast<float>(c.fy),
          static_cast<float>(c.cx),
          static_cast<float>(c.cy),
          c.width,
          c.height};
}

inline V3 to_v3(const Eigen::Vector3d& v) {
  return {static_cast<float>(v.x()), static_cast<float>(v.y()), static_cast<float>(v.z())};
}

// `src` as reference `ref` sees it: the relative pose composed in double, then rounded once. `grey` and
// `depth` (may be null) are the source's pixels on the device the step runs on.
inline Source relative_source(const Camera& ref, const Camera& src, const float* grey, const float* depth) {
  const Eigen::Matrix3d R = src.R * ref.R.transpose();
  const Eigen::Vector3d t = src.t - R * ref.t;
  Source s;
  s.cam = view_geometry(src);
  for (int i = 0; i < 9; ++i) s.R.m[i] = static_cast<float>(R(i / 3, i % 3));
  s.t = to_v3(t);
  s.centre = to_v3(-R.transpose() * t);
  s.grey = grey;
  s.depth = depth;
  return s;
}

}  // namespace gaps::pm

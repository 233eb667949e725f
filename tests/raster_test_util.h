#pragma once
// The random scenes of the rasterizer tests (rasterizer_test.cpp, and gpu/rasterizer_cuda_test.cpp, which
// draws its own Gaussians for the CUDA comparisons) and the camera they are seen from.
#include <ATen/ATen.h>
#include <Eigen/Geometry>
#include "gs_trainer/raster/raster_math.h"

namespace gaps::test {

struct RandomScene {
  at::Tensor means, quats, scales, opacities, features, viewmat;
  raster::Intrinsics K;
};

// A camera looking down +z from a slightly rotated pose, with the principal point a little off centre
// (so that no symmetry hides an error), for a width x height image.
inline void place_camera(RandomScene& s, int width, int height, const at::TensorOptions& opts) {
  Eigen::Matrix3d R = Eigen::AngleAxisd(0.1, Eigen::Vector3d(0.3, 1.0, 0.2).normalized()).toRotationMatrix();
  s.viewmat = at::eye(4, opts);
  for (int r = 0; r < 3; ++r)
    for (int c = 0; c < 3; ++c) s.viewmat[r][c] = R(r, c);
  s.viewmat[0][3] = 0.05;
  s.viewmat[2][3] = 0.3;
  s.K = {0.9 * width, 0.9 * width, 0.5 * width + 0.7, 0.5 * height - 0.4, width, height};
}

}  // namespace gaps::test

#pragma once
// The random scenes of the rasterizer tests (rasterizer_test.cpp, and gpu/rasterizer_cuda_test.cpp, which
// draws its own Gaussians for the CUDA comparisons) and the camera they are seen from.
#include <ATen/ATen.h>
#include <Eigen/Geometry>
#include "gs_trainer/model/gaussians.h"
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

// A random Gaussian model 2 to 4 units down +z, mostly within the view of a camera at the origin, with SH degree
// `degree` in use and faint, varied opacities (overlaps stay visible).
inline GaussianModel random_model(int n, uint64_t seed, at::ScalarType dtype = at::kDouble, int degree = 3) {
  at::manual_seed(seed);
  auto o = at::TensorOptions().dtype(dtype);
  GaussianModel m;
  m.max_sh_degree = degree;
  m.sh_degree = degree;
  m.means = at::rand({n, 3}, o) * at::tensor({2.0, 1.6, 2.0}, o) - at::tensor({1.0, 0.8, -2.0}, o);
  m.log_scales = at::log(at::rand({n, 3}, o) * 0.25 + 0.05);
  m.quats = at::randn({n, 4}, o);
  m.opacity_logits = at::logit(at::rand({n}, o) * 0.25 + 0.08);
  m.sh_dc = at::randn({n, 1, 3}, o) * 0.5;
  m.sh_rest = at::randn({n, (degree + 1) * (degree + 1) - 1, 3}, o) * 0.1;
  return m;
}

}  // namespace gaps::test

#pragma once
// A coloured point cloud: what initialisations make, scenes ship and PLY files hold.
#include <ATen/Tensor.h>

namespace gaps {

struct PointCloud {
  at::Tensor xyz;  // N x 3 float32
  at::Tensor rgb;  // N x 3 float32 in [0, 1]
};

}  // namespace gaps

#include "gs_trainer/scene/camera.h"

#include <ATen/ATen.h>

namespace gaps {

at::Tensor Camera::viewmat() const {
  at::Tensor m = at::eye(4, at::kFloat);
  auto a = m.accessor<float, 2>();
  for (int r = 0; r < 3; ++r) {
    for (int c = 0; c < 3; ++c) a[r][c] = static_cast<float>(R(r, c));
    a[r][3] = static_cast<float>(t(r));
  }
  return m;
}

at::Tensor Camera::intrinsics() const {
  at::Tensor k = at::zeros({3, 3}, at::kFloat);
  auto a = k.accessor<float, 2>();
  a[0][0] = static_cast<float>(fx);
  a[1][1] = static_cast<float>(fy);
  a[0][2] = static_cast<float>(cx);
  a[1][2] = static_cast<float>(cy);
  a[2][2] = 1.0f;
  return k;
}

Camera Camera::resized(int new_width, int new_height) const {
  Camera c = *this;
  const double sx = static_cast<double>(new_width) / width;
  const double sy = static_cast<double>(new_height) / height;
  c.width = new_width;
  c.height = new_height;
  c.fx *= sx;
  c.cx *= sx;
  c.fy *= sy;
  c.cy *= sy;
  return c;
}

}  // namespace gaps

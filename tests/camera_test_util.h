#pragma once
// A small pinhole camera for the codec and service tests: width x height pixels, f = 20, the principal point at the
// centre, translated by -x along the x axis, named after x (so cameras at different x have different names).
#include <string>

#include "gs_trainer/scene/camera.h"

namespace gaps::test {

inline Camera camera_on_x_axis(double x, int width = 24, int height = 18) {
  Camera c;
  c.name = "cam" + std::to_string(static_cast<int>(x * 10)) + ".png";
  c.width = width;
  c.height = height;
  c.fx = c.fy = 20;
  c.cx = width / 2.0;
  c.cy = height / 2.0;
  c.t = Eigen::Vector3d(-x, 0, 0);
  return c;
}

}  // namespace gaps::test

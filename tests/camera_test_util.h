#pragma once
// A pinhole camera for ray-cast test scenes (reproject_generator_test.cpp, restore_generator_test.cpp, and the
// intrinsics of synthetic_stereo.h's look_at).
#include <Eigen/Dense>

#include "gs_trainer/scene/camera.h"

namespace gaps::test {

// Looks down +z (R = identity) from `center`, principal point at the image centre.
inline Camera camera_looking_down_z(int width, int height, double focal, const Eigen::Vector3d& center) {
  Camera c;
  c.width = width;
  c.height = height;
  c.fx = c.fy = focal;
  c.cx = width / 2.0;
  c.cy = height / 2.0;
  c.R = Eigen::Matrix3d::Identity();
  c.t = -center;
  return c;
}

}  // namespace gaps::test

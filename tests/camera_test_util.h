#pragma once
// Pinhole cameras for ray-cast test scenes (reproject_generator_test.cpp, restore_generator_test.cpp, and the
// intrinsics of synthetic_stereo.h's look_at) and for the codec and service tests.
#include <string>

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

// A small camera of the codec and service tests: f = 20 at (x, 0, 0), named after x (cameras at different x have
// different names).
inline Camera camera_on_x_axis(double x, int width = 24, int height = 18) {
  Camera c = camera_looking_down_z(width, height, 20, Eigen::Vector3d(x, 0, 0));
  c.name = "cam" + std::to_string(static_cast<int>(x * 10)) + ".png";
  return c;
}

}  // namespace gaps::test

#pragma once
// A pinhole camera in OpenCV convention (x right, y down, z forward), world-to-camera extrinsics.
// Pixel (i, j) covers [i, i+1) x [j, j+1); its centre is (i + 0.5, j + 0.5).
#include <filesystem>
#include <string>
#include <vector>

#include <ATen/Tensor.h>
#include <Eigen/Core>

namespace gaps {

struct Camera {
  std::string name;                  // image file name, e.g. "image003.png"
  std::filesystem::path image_path;  // file the pixels come from (may be larger than width x height)
  int width = 0;
  int height = 0;
  double fx = 0, fy = 0, cx = 0, cy = 0;
  Eigen::Matrix3d R = Eigen::Matrix3d::Identity();  // world -> camera rotation
  Eigen::Vector3d t = Eigen::Vector3d::Zero();      // world -> camera translation
  double near = 0.0, far = 0.0;                     // scene depth bounds when the format gives them (else 0)
  // Lens distortion in OpenCV order (k1, k2, p1, p2[, k3]); empty for an ideal pinhole. Images are
  // undistorted on load, so the rasterizer only ever sees the pinhole above.
  std::vector<double> distortion;

  Eigen::Vector3d center() const { return -R.transpose() * t; }
  Eigen::Vector3d forward() const { return R.row(2).transpose(); }  // viewing direction in world space
  // 4x4 float32 world-to-camera matrix and 3x3 float32 intrinsics (CPU tensors).
  at::Tensor viewmat() const;
  at::Tensor intrinsics() const;
  // The same camera seen at another image size: intrinsics scaled per axis.
  Camera resized(int new_width, int new_height) const;
};

}  // namespace gaps

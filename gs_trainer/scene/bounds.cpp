#include "gs_trainer/scene/bounds.h"

#include <algorithm>
#include <cmath>
#include <random>

#include <ATen/ATen.h>
#include <Eigen/SVD>

namespace gaps {

PointCloud random_points_in_views(const std::vector<Camera>& cameras, int64_t count, double fallback_far,
                                  uint64_t seed) {
  std::mt19937_64 rng(seed);
  std::uniform_real_distribution<double> u(0.0, 1.0);
  std::uniform_int_distribution<size_t> pick(0, cameras.size() - 1);
  at::Tensor xyz = at::empty({count, 3}, at::kFloat);
  auto a = xyz.accessor<float, 2>();
  for (int64_t i = 0; i < count; ++i) {
    const Camera& c = cameras[pick(rng)];
    const double near = c.near > 0 ? c.near : 0.1, far = c.far > near ? c.far : fallback_far;
    const double depth = near + (far - near) * u(rng);
    const Eigen::Vector3d ray((u(rng) * c.width - c.cx) / c.fx, (u(rng) * c.height - c.cy) / c.fy, 1.0);
    const Eigen::Vector3d p = c.R.transpose() * (ray * depth - c.t);
    for (int j = 0; j < 3; ++j) a[i][j] = static_cast<float>(p(j));
  }
  at::Tensor rgb = at::empty({count, 3}, at::kFloat);
  float* r = rgb.data_ptr<float>();
  for (int64_t i = 0; i < count * 3; ++i) r[i] = static_cast<float>(u(rng));
  return {xyz, rgb};
}

std::optional<Eigen::Vector3d> optical_axes_target(const std::vector<Camera>& cameras) {
  // Least squares: sum over cameras of (I - d d^T)(x - c) = 0.
  Eigen::Matrix3d A = Eigen::Matrix3d::Zero();
  Eigen::Vector3d b = Eigen::Vector3d::Zero();
  for (const auto& c : cameras) {
    const Eigen::Vector3d d = c.forward().normalized();
    const Eigen::Matrix3d P = Eigen::Matrix3d::Identity() - d * d.transpose();
    A += P;
    b += P * c.center();
  }
  Eigen::JacobiSVD<Eigen::Matrix3d> svd(A, Eigen::ComputeFullU | Eigen::ComputeFullV);
  if (cameras.size() < 2 || svd.singularValues()(2) < 1e-6 * svd.singularValues()(0)) return std::nullopt;
  const Eigen::Vector3d target = svd.solve(b);
  for (const auto& c : cameras)
    if ((target - c.center()).dot(c.forward()) <= 0) return std::nullopt;
  return target;
}

double default_far_bound(const std::vector<Camera>& cameras) {
  const double fallback = 2.0 * cameras_extent(cameras) + 1.0;
  const std::optional<Eigen::Vector3d> target = optical_axes_target(cameras);
  if (!target) return fallback;
  double far = 0;
  for (const auto& c : cameras) far = std::max(far, 2.0 * (*target - c.center()).norm());
  return std::max(far, fallback);
}

double cameras_extent(const std::vector<Camera>& cameras) {
  Eigen::Vector3d centre = Eigen::Vector3d::Zero();
  for (const auto& c : cameras) centre += c.center();
  centre /= static_cast<double>(cameras.size());
  double radius = 0;
  for (const auto& c : cameras) radius = std::max(radius, (c.center() - centre).norm());
  return 1.1 * std::max(radius, 1e-6);
}

}  // namespace gaps

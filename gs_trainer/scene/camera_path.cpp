#include "gs_trainer/scene/camera_path.h"

#include <algorithm>
#include <cmath>
#include <limits>

#include <ATen/ATen.h>
#include <Eigen/Geometry>
#include "absl/strings/match.h"
#include "absl/strings/str_cat.h"
#include "common/status_macros.h"
#include "gs_trainer/scene/bounds.h"
#include "gs_trainer/scene/cameras_json.h"

namespace gaps {
namespace {

constexpr double kPi = 3.14159265358979323846;
// LLFF's spiral: two turns, the depth axis oscillating at half the turning rate.
constexpr double kSpiralTurns = 2.0;
constexpr double kSpiralDepthRate = 0.5;

Eigen::Vector3d mean_centre(const std::vector<Camera>& cameras) {
  Eigen::Vector3d sum = Eigen::Vector3d::Zero();
  for (const auto& c : cameras) sum += c.center();
  return sum / static_cast<double>(cameras.size());
}

Eigen::Vector3d mean_forward(const std::vector<Camera>& cameras) {
  Eigen::Vector3d sum = Eigen::Vector3d::Zero();
  for (const auto& c : cameras) sum += c.forward();
  return sum.normalized();
}

// A unit vector orthogonal to `v` (for degenerate cases: no preferred direction).
Eigen::Vector3d any_orthogonal(const Eigen::Vector3d& v) {
  const Eigen::Vector3d axis = std::abs(v.x()) < 0.9 ? Eigen::Vector3d::UnitX() : Eigen::Vector3d::UnitY();
  return v.cross(axis).normalized();
}

// The cameras' mean pose: their mean centre, looking along their mean viewing direction, up their mean up.
Camera mean_pose(const std::vector<Camera>& cameras) {
  const Eigen::Vector3d centre = mean_centre(cameras);
  return look_at(cameras.front(), centre, centre + mean_forward(cameras), mean_up(cameras));
}

// The 90th percentile of |values| (nearest rank).
double percentile90_abs(std::vector<double> values) {
  for (double& v : values) v = std::abs(v);
  std::sort(values.begin(), values.end());
  const size_t rank = static_cast<size_t>(std::ceil(0.9 * values.size()));
  return values[std::max<size_t>(rank, 1) - 1];
}

// Frame k of `frames` as a fraction of a full loop (the first frame at 0, the last one step before 1).
double loop_fraction(int k, int frames) { return static_cast<double>(k) / frames; }

Eigen::Vector3d catmull_rom(const Eigen::Vector3d& p0, const Eigen::Vector3d& p1, const Eigen::Vector3d& p2,
                            const Eigen::Vector3d& p3, double u) {
  return 0.5 * (2.0 * p1 + (p2 - p0) * u + (2.0 * p0 - 5.0 * p1 + 4.0 * p2 - p3) * u * u +
                (3.0 * p1 - p0 - 3.0 * p2 + p3) * u * u * u);
}

// The camera at spline parameter s in [0, n - 1] over `cameras`.
Camera interpolated_at(const std::vector<Camera>& cameras, double s) {
  const int n = static_cast<int>(cameras.size());
  const int i = std::clamp(static_cast<int>(std::floor(s)), 0, std::max(n - 2, 0));
  const double u = std::clamp(s - i, 0.0, 1.0);
  const auto centre_of = [&](int j) { return cameras[std::clamp(j, 0, n - 1)].center(); };
  Camera out = cameras.front();  // every frame at the first camera's intrinsics, as the other generated paths
  out.distortion.clear();
  out.near = out.far = 0.0;
  const Eigen::Quaterniond a(cameras[i].R);
  const Eigen::Quaterniond b(cameras[std::min(i + 1, n - 1)].R);
  out.R = a.slerp(u, b).normalized().toRotationMatrix();
  out.t = -out.R * catmull_rom(centre_of(i - 1), centre_of(i), centre_of(i + 1), centre_of(i + 2), u);
  return out;
}

void name_frames(std::vector<Camera>& frames) {
  for (size_t k = 0; k < frames.size(); ++k) {
    std::string digits = std::to_string(k);
    frames[k].name = std::string(5 - std::min<size_t>(digits.size(), 5), '0') + digits + ".png";
  }
}

}  // namespace

absl::StatusOr<std::pair<double, double>> path_depth_bounds(const std::vector<Camera>& cameras,
                                                            const at::Tensor& points) {
  double near = std::numeric_limits<double>::infinity(), far = 0.0;
  for (const auto& c : cameras) {
    if (c.near > 0) near = std::min(near, c.near);
    far = std::max(far, c.far);
  }
  if (std::isfinite(near) && far > near) return std::make_pair(near, far);
  const at::Tensor xyz = points.defined() ? points.to(at::kDouble).cpu() : at::empty({0, 3}, at::kDouble);
  std::vector<at::Tensor> depths;
  for (const auto& c : cameras) {
    const Eigen::Vector3d f = c.forward();
    const at::Tensor z = at::matmul(xyz, at::tensor({f.x(), f.y(), f.z()}, at::kDouble)) + c.t.z();
    depths.push_back(z.masked_select(z > 1e-6));
  }
  const at::Tensor all = depths.empty() ? at::empty({0}, at::kDouble) : std::get<0>(at::cat(depths).sort());
  if (all.numel() == 0)
    return absl::InvalidArgumentError("no depth bounds: the cameras give none and no point lies in front of them");
  const auto percentile = [&](double q) {
    return all[static_cast<int64_t>(std::round(q * static_cast<double>(all.numel() - 1)))].item<double>();
  };
  const double lo = percentile(0.01), hi = percentile(0.99);
  return std::make_pair(lo, std::max(hi, lo * (1.0 + 1e-6)));
}

Eigen::Vector3d mean_up(const std::vector<Camera>& cameras) {
  Eigen::Vector3d sum = Eigen::Vector3d::Zero();
  for (const auto& c : cameras) sum -= c.R.row(1).transpose();
  return sum.normalized();
}

Camera look_at(const Camera& intrinsics, const Eigen::Vector3d& position, const Eigen::Vector3d& target,
               const Eigen::Vector3d& up) {
  const Eigen::Vector3d z = (target - position).normalized();
  Eigen::Vector3d x = z.cross(up);
  x = x.norm() > 1e-9 ? x.normalized() : any_orthogonal(z);  // looking straight along `up`
  const Eigen::Vector3d y = z.cross(x);
  Camera out = intrinsics;
  out.distortion.clear();
  out.near = out.far = 0.0;
  out.R.row(0) = x.transpose();
  out.R.row(1) = y.transpose();
  out.R.row(2) = z.transpose();
  out.t = -out.R * position;
  return out;
}

double spiral_focus_depth(double near, double far) {
  constexpr double kWeight = 0.75;
  return 1.0 / ((1.0 - kWeight) / (0.9 * near) + kWeight / (5.0 * far));
}

Eigen::Vector3d scene_centre(const PathScene& scene) {
  if (const std::optional<Eigen::Vector3d> target = optical_axes_target(scene.train)) return *target;
  return mean_centre(scene.train) + spiral_focus_depth(scene.near, scene.far) * mean_forward(scene.train);
}

std::vector<Camera> orbit_path(const PathScene& scene, int frames) {
  const Eigen::Vector3d centre = scene_centre(scene);
  const Eigen::Vector3d up = mean_up(scene.train);
  double distance = 0.0, height = 0.0;
  for (const auto& c : scene.train) {
    distance += (c.center() - centre).norm();
    height += (c.center() - centre).dot(up);
  }
  distance /= static_cast<double>(scene.train.size());
  height /= static_cast<double>(scene.train.size());
  // The circle's radius keeps the mean distance at the mean height; it starts at the first camera's azimuth.
  const double radius = std::sqrt(std::max(distance * distance - height * height, 0.0));
  Eigen::Vector3d e1 = scene.train.front().center() - centre;
  e1 -= e1.dot(up) * up;
  e1 = e1.norm() > 1e-9 ? e1.normalized() : any_orthogonal(up);
  const Eigen::Vector3d e2 = up.cross(e1);
  std::vector<Camera> path;
  for (int k = 0; k < frames; ++k) {
    const double angle = 2.0 * kPi * loop_fraction(k, frames);
    const Eigen::Vector3d position = centre + height * up + radius * (std::cos(angle) * e1 + std::sin(angle) * e2);
    path.push_back(look_at(scene.train.front(), position, centre, up));
  }
  name_frames(path);
  return path;
}

std::vector<Camera> spiral_path(const PathScene& scene, int frames) {
  const Camera mean = mean_pose(scene.train);
  const Eigen::Vector3d centre = mean.center();
  std::vector<double> dx, dy, dz;
  for (const auto& c : scene.train) {
    const Eigen::Vector3d local = mean.R * (c.center() - centre);
    dx.push_back(local.x());
    dy.push_back(local.y());
    dz.push_back(local.z());
  }
  const Eigen::Vector3d radii(percentile90_abs(dx), percentile90_abs(dy), percentile90_abs(dz));
  const Eigen::Vector3d focus = centre + spiral_focus_depth(scene.near, scene.far) * mean.forward();
  const Eigen::Vector3d up = -mean.R.row(1).transpose();
  std::vector<Camera> path;
  for (int k = 0; k < frames; ++k) {
    const double angle = 2.0 * kPi * kSpiralTurns * loop_fraction(k, frames);
    // LLFF's (cos θ, -sin θ, -sin θ/2) in its right-up-back axes, here in OpenCV's right-down-forward ones.
    const Eigen::Vector3d local(std::cos(angle) * radii.x(), std::sin(angle) * radii.y(),
                                std::sin(kSpiralDepthRate * angle) * radii.z());
    path.push_back(look_at(scene.train.front(), centre + mean.R.transpose() * local, focus, up));
  }
  name_frames(path);
  return path;
}

std::vector<Camera> interp_path(const PathScene& scene, int frames) {
  const int n = static_cast<int>(scene.train.size());
  std::vector<Camera> path;
  for (int k = 0; k < frames; ++k) {
    const double s = frames > 1 ? static_cast<double>(k) * (n - 1) / (frames - 1) : 0.0;
    path.push_back(interpolated_at(scene.train, s));
  }
  name_frames(path);
  return path;
}

absl::StatusOr<std::vector<Camera>> camera_path(const std::string& path, const PathScene& scene, int frames) {
  const bool file = absl::EndsWithIgnoreCase(path, ".json");
  if (!file && path != "test" && path != "orbit" && path != "spiral" && path != "interp")
    return absl::InvalidArgumentError(
        absl::StrCat("path '", path, "': unknown; one of orbit, spiral, interp, test, or a cameras .json file"));
  if (frames < 1 && !file && path != "test") return absl::InvalidArgumentError("the number of frames must be >= 1");
  std::vector<Camera> cameras;
  if (file) {
    GAPS_ASSIGN_OR_RETURN(const std::vector<CameraRecord> records, read_cameras_json(path));
    for (const auto& r : records) cameras.push_back(r.camera);
  } else if (path == "test") {
    cameras = scene.test;
  } else if (scene.train.empty()) {
    return absl::InvalidArgumentError(absl::StrCat("path ", path, " needs the training cameras; there are none"));
  } else if (path == "orbit") {
    return orbit_path(scene, frames);
  } else if (path == "spiral") {
    return spiral_path(scene, frames);
  } else {
    return interp_path(scene, frames);
  }
  if (cameras.empty()) return absl::InvalidArgumentError(absl::StrCat("path ", path, ": no cameras"));
  name_frames(cameras);
  return cameras;
}

std::string camera_path_name(const std::string& path) {
  if (absl::EndsWithIgnoreCase(path, ".json")) return std::filesystem::path(path).stem().string();
  return path;
}

}  // namespace gaps

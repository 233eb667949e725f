#include "gs_trainer/synthetic.h"

#include <cmath>
#include <fstream>

#include <ATen/ATen.h>
#include <ATen/core/grad_mode.h>
#include <Eigen/Geometry>
#include <nlohmann/json.hpp>
#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "common/image_io.h"
#include "common/spherical_harmonics.h"
#include "common/status_macros.h"
#include "gs_trainer/model/render.h"

namespace gaps {
namespace {

// Flat, camera-facing discs on a plane z = depth with a colour pattern that has detail at several scales.
PointCloud textured_backdrop(int nx, int ny, double depth) {
  const auto u = at::linspace(-2.0, 2.0, nx, at::kFloat), v = at::linspace(-1.5, 1.5, ny, at::kFloat);
  auto grid = at::meshgrid({v, u}, "ij");
  const auto y = grid[0].reshape(-1), x = grid[1].reshape(-1);
  const auto checker = ((at::floor(x * 2) + at::floor(y * 2)).remainder(2)).to(at::kFloat);
  const auto r = 0.5 + 0.4 * at::sin(x * 5.0) * (0.5 + 0.5 * checker);
  const auto g = 0.3 + 0.5 * checker * (0.5 + 0.5 * at::cos(y * 7.0));
  const auto b = 0.5 + 0.4 * at::sin((x + y) * 3.0);
  return {at::stack({x, y, at::full_like(x, depth)}, 1), at::stack({r, g, b}, 1).clamp(0.0, 1.0)};
}

PointCloud sphere(double cx, double cy, double cz, double radius, int count, double r, double g, double b,
                  uint64_t seed) {
  at::manual_seed(seed);
  auto dirs = at::randn({count, 3});
  dirs = dirs / dirs.norm(2, {1}, true);
  const auto xyz = dirs * radius + at::tensor({cx, cy, cz}, at::kFloat);
  const auto shade = 0.6 + 0.4 * dirs.select(1, 1).neg().unsqueeze(1);  // lit from above
  const auto rgb = (at::tensor({r, g, b}, at::kFloat) * shade).clamp(0.0, 1.0);
  return {xyz, rgb};
}

// Camera at `eye` looking at `target`, OpenCV axes (y down).
Camera look_at(const Eigen::Vector3d& eye, const Eigen::Vector3d& target, int w, int h, double f) {
  const Eigen::Vector3d z = (target - eye).normalized();
  const Eigen::Vector3d x = Eigen::Vector3d(0, 1, 0).cross(z).normalized();  // world y points down
  const Eigen::Vector3d y = z.cross(x);
  Camera c;
  c.R.row(0) = x.transpose();
  c.R.row(1) = y.transpose();
  c.R.row(2) = z.transpose();
  c.t = -c.R * eye;
  c.width = w;
  c.height = h;
  c.fx = c.fy = f;
  c.cx = w / 2.0;
  c.cy = h / 2.0;
  return c;
}

nlohmann::json opengl_c2w(const Camera& c) {
  // nerfstudio stores camera-to-world with OpenGL axes (y up, z backwards).
  Eigen::Matrix4d c2w = Eigen::Matrix4d::Identity();
  c2w.block<3, 3>(0, 0) = c.R.transpose();
  c2w.block<3, 1>(0, 3) = c.center();
  c2w.col(1) *= -1.0;
  c2w.col(2) *= -1.0;
  nlohmann::json m = nlohmann::json::array();
  for (int r = 0; r < 4; ++r) m.push_back({c2w(r, 0), c2w(r, 1), c2w(r, 2), c2w(r, 3)});
  return m;
}

}  // namespace

GaussianModel synthetic_ground_truth(uint64_t seed) {
  const PointCloud parts[] = {textured_backdrop(120, 90, 4.0), sphere(-0.6, 0.2, 2.6, 0.35, 1500, 0.9, 0.2, 0.2, seed),
                              sphere(0.5, -0.3, 2.2, 0.3, 1200, 0.2, 0.8, 0.3, seed + 1),
                              sphere(0.1, 0.5, 3.0, 0.25, 900, 0.2, 0.3, 0.9, seed + 2)};
  std::vector<at::Tensor> xyz, rgb;
  for (const auto& p : parts) {
    xyz.push_back(p.xyz);
    rgb.push_back(p.rgb);
  }
  GaussianModel m = gaussians_from_points({at::cat(xyz), at::cat(rgb)}, 0);
  m.opacity_logits.fill_(4.0);  // nearly opaque surfaces
  m.log_scales = m.log_scales + std::log(1.2);
  return m;
}

absl::Status write_synthetic_scene(const std::filesystem::path& dir, const SyntheticSceneOptions& o) {
  at::AutoGradMode no_grad(false);
  std::filesystem::create_directories(dir / "images");
  const GaussianModel truth = synthetic_ground_truth(o.seed);
  RenderOptions render_options;
  render_options.background = at::zeros({3});
  const double focal = 0.9 * o.width;
  nlohmann::json j;
  j["fl_x"] = focal;
  j["fl_y"] = focal;
  j["cx"] = o.width / 2.0;
  j["cy"] = o.height / 2.0;
  j["w"] = o.width;
  j["h"] = o.height;
  j["camera_model"] = "OPENCV";
  for (int i = 0; i < o.images; ++i) {
    // A forward-facing arc: the cameras spread over a small ellipse, all looking at the scene centre.
    const double a = 2.0 * M_PI * i / o.images;
    const Eigen::Vector3d eye(0.6 * std::cos(a), 0.35 * std::sin(a), 0.0);
    const Camera cam = look_at(eye, Eigen::Vector3d(0, 0, 3.0), o.width, o.height, focal);
    const std::string name = absl::StrFormat("images/frame_%03d.png", i);
    GAPS_RETURN_IF_ERROR(write_png(dir / name, render(truth, cam, render_options).rgb.clamp(0.0, 1.0)));
    j["frames"].push_back({{"file_path", name}, {"transform_matrix", opengl_c2w(cam)}});
  }
  std::ofstream f(dir / "transforms.json");
  f << j.dump(2) << "\n";
  if (!f) return absl::DataLossError(absl::StrCat((dir / "transforms.json").string(), ": write failed"));
  return absl::OkStatus();
}

}  // namespace gaps

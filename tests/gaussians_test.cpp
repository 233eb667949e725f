// Gaussian model: initialisation from points, random points in the views, PLY round trip, SH maths.
#include <cmath>
#include <filesystem>
#include <fstream>

#include <unistd.h>

#include <ATen/ATen.h>
#include <gtest/gtest.h>
#include <Eigen/Geometry>

#include "common/ply.h"
#include "common/spherical_harmonics.h"
#include "gs_trainer/model/gaussians.h"
#include "gs_trainer/model/render.h"

namespace gaps {
namespace {

std::filesystem::path temp_path(const std::string& name) {
  return std::filesystem::temp_directory_path() / ("gaps_gaussians_test_" + std::to_string(::getpid()) + "_" + name);
}

TEST(GaussiansFromPoints, MatchesThe3dgsInitialisation) {
  // Four points on a unit square: each has neighbours at distances 1, 1 and sqrt(2).
  PointCloud pc{at::tensor({0.f, 0.f, 0.f, 1.f, 0.f, 0.f, 0.f, 1.f, 0.f, 1.f, 1.f, 0.f}).view({4, 3}),
                at::full({4, 3}, 0.75f)};
  const auto m = gaussians_from_points(pc, 3);
  EXPECT_EQ(m.size(), 4);
  const double expected_scale = std::sqrt((1.0 + 1.0 + 2.0) / 3.0);
  EXPECT_NEAR(at::exp(m.log_scales).max().item<double>(), expected_scale, 1e-5);
  EXPECT_NEAR(at::exp(m.log_scales).min().item<double>(), expected_scale, 1e-5);
  EXPECT_NEAR(m.opacities().mean().item<double>(), 0.1, 1e-6);
  EXPECT_TRUE(at::allclose(m.quats.select(1, 0), at::ones({4})));
  EXPECT_NEAR(sh_dc_to_rgb(m.sh_dc).mean().item<double>(), 0.75, 1e-6);
  EXPECT_EQ(m.sh_rest.sizes(), at::IntArrayRef({4, 15, 3}));
}

TEST(RandomPointsInViews, LieInsideTheFrustaBetweenNearAndFar) {
  Camera c;
  c.width = 100;
  c.height = 80;
  c.fx = c.fy = 90;
  c.cx = 50;
  c.cy = 40;
  c.near = 1.0;
  c.far = 5.0;
  c.t = Eigen::Vector3d(0.2, -0.1, 0.3);
  const auto pc = random_points_in_views({c}, 2000, 10.0, 3);
  const auto xyz = pc.xyz.to(at::kDouble);
  for (int64_t i = 0; i < 2000; i += 37) {
    const Eigen::Vector3d p(xyz[i][0].item<double>(), xyz[i][1].item<double>(), xyz[i][2].item<double>());
    const Eigen::Vector3d q = c.R * p + c.t;
    EXPECT_GE(q.z(), 1.0 - 1e-4);
    EXPECT_LE(q.z(), 5.0 + 1e-4);
    const double u = c.fx * q.x() / q.z() + c.cx, v = c.fy * q.y() / q.z() + c.cy;
    EXPECT_GE(u, -1e-3);
    EXPECT_LE(u, c.width + 1e-3);
    EXPECT_GE(v, -1e-3);
    EXPECT_LE(v, c.height + 1e-3);
  }
  EXPECT_TRUE((pc.rgb >= 0).all().item<bool>() && (pc.rgb <= 1).all().item<bool>());
}

TEST(CamerasExtent, IsTheEnclosingRadiusTimesOnePointOne) {
  Camera a, b;
  a.t = Eigen::Vector3d(-1, 0, 0);  // centre (1, 0, 0)
  b.t = Eigen::Vector3d(1, 0, 0);   // centre (-1, 0, 0)
  EXPECT_NEAR(cameras_extent({a, b}), 1.1, 1e-12);
}

TEST(DefaultFarBound, IsTwiceTheDistanceToWhereTheAxesMeet) {
  // Two cameras 2 apart on the x axis, both looking at (0, 0, 3).
  std::vector<Camera> cams(2);
  for (int i = 0; i < 2; ++i) {
    const Eigen::Vector3d eye(i == 0 ? -1.0 : 1.0, 0, 0), target(0, 0, 3);
    const Eigen::Vector3d z = (target - eye).normalized(), x = Eigen::Vector3d(0, 1, 0).cross(z).normalized();
    cams[i].R.row(0) = x.transpose();
    cams[i].R.row(1) = z.cross(x).transpose();
    cams[i].R.row(2) = z.transpose();
    cams[i].t = -cams[i].R * eye;
  }
  EXPECT_NEAR(default_far_bound(cams), 2.0 * std::sqrt(10.0), 1e-9);
  // Parallel axes never meet: the extent-based fallback.
  std::vector<Camera> parallel(2);
  parallel[1].t = Eigen::Vector3d(-1, 0, 0);
  EXPECT_NEAR(default_far_bound(parallel), 2.0 * cameras_extent(parallel) + 1.0, 1e-12);
}

TEST(GaussiansPly, RoundTripKeepsEveryParameter) {
  at::manual_seed(0);
  GaussianModel m;
  m.max_sh_degree = 3;
  m.means = at::randn({50, 3});
  m.log_scales = at::randn({50, 3});
  m.quats = at::randn({50, 4});
  m.opacity_logits = at::randn({50});
  m.sh_dc = at::randn({50, 1, 3});
  m.sh_rest = at::randn({50, 15, 3});
  const auto path = temp_path("model.ply");
  ASSERT_TRUE(save_gaussians_ply(m, path).ok());
  auto loaded = load_gaussians_ply(path);
  ASSERT_TRUE(loaded.ok()) << loaded.status();
  EXPECT_EQ(loaded->max_sh_degree, 3);
  auto a = m.parameters(), b = loaded->parameters();
  for (size_t i = 0; i < a.size(); ++i) EXPECT_TRUE(at::equal(*a[i], *b[i])) << "parameter " << i;
  // The standard layout: 62 float properties, f_rest channel-major.
  auto raw = read_ply_vertices(path);
  ASSERT_TRUE(raw.ok());
  EXPECT_EQ(raw->names.size(), 62u);
  EXPECT_EQ(raw->names[9], "f_rest_0");
  EXPECT_FLOAT_EQ(raw->properties["f_rest_1"][7].item<float>(), m.sh_rest[7][1][0].item<float>());
  EXPECT_FLOAT_EQ(raw->properties["f_rest_15"][7].item<float>(), m.sh_rest[7][0][1].item<float>());
  std::filesystem::remove(path);
}

// A model in front of a camera, with every SH band non-zero, so that each parameter shows in the render.
GaussianModel visible_model(int n, int degree) {
  at::manual_seed(1);
  GaussianModel m;
  m.max_sh_degree = degree;
  m.sh_degree = degree;
  m.means = at::rand({n, 3}) * 2 - 1;
  m.means.select(1, 2).add_(4.0);
  m.log_scales = at::log(at::rand({n, 3}) * 0.15 + 0.02);
  m.quats = at::randn({n, 4});
  m.opacity_logits = at::randn({n});
  m.sh_dc = at::randn({n, 1, 3}) * 0.5;
  m.sh_rest = at::randn({n, sh_coefficients(degree) - 1, 3}) * 0.2;
  return m;
}

Camera front_camera() {
  Camera c;
  c.width = 40;
  c.height = 30;
  c.fx = c.fy = 35;
  c.cx = 20.3;
  c.cy = 14.8;
  c.R = Eigen::AngleAxisd(0.2, Eigen::Vector3d(0.2, 1.0, 0.1).normalized()).toRotationMatrix();
  c.t = Eigen::Vector3d(0.3, -0.1, 0.5);
  return c;
}

TEST(GaussiansPly, AModelWrittenAndReadBackRendersIdentically) {
  const GaussianModel m = visible_model(300, 3);
  const auto path = temp_path("render_round_trip.ply");
  ASSERT_TRUE(save_gaussians_ply(m, path).ok());
  auto loaded = load_gaussians_ply(path);
  ASSERT_TRUE(loaded.ok()) << loaded.status();
  EXPECT_EQ(loaded->sh_degree, 3);
  const at::Tensor before = render(m, front_camera()).rgb, after = render(*loaded, front_camera()).rgb;
  EXPECT_GT(before.std().item<float>(), 0.01f);  // something is drawn
  EXPECT_TRUE(at::equal(before, after));
  std::filesystem::remove(path);
}

// The reference code's layout as plyfile writes it (binary float properties x.. rot_3 with normals), and as
// other tools do: ASCII, doubles, other property orders, no normals, a lower SH degree.
TEST(GaussiansPly, LoadsEveryPropertyOfTheReferenceLayoutsAtEverySHDegree) {
  for (int degree : {0, 1, 2, 3}) {
    const GaussianModel m = visible_model(7, degree);
    const int rest = sh_coefficients(degree) - 1;
    // Columns by name, the f_rest ones channel-major as the reference code stores them.
    std::vector<std::pair<std::string, at::Tensor>> columns;
    const char* xyz[] = {"x", "y", "z"};
    for (int i = 0; i < 3; ++i) columns.push_back({xyz[i], m.means.select(1, i)});
    columns.push_back({"opacity", m.opacity_logits});
    for (int i = 0; i < 4; ++i) columns.push_back({"rot_" + std::to_string(i), m.quats.select(1, i)});
    for (int i = 0; i < 3; ++i) columns.push_back({"scale_" + std::to_string(i), m.log_scales.select(1, i)});
    for (int i = 0; i < 3; ++i) columns.push_back({"f_dc_" + std::to_string(i), m.sh_dc.select(1, 0).select(1, i)});
    for (int c = 0; c < 3; ++c)
      for (int k = 0; k < rest; ++k)
        columns.push_back({"f_rest_" + std::to_string(c * rest + k), m.sh_rest.select(1, k).select(1, c)});
    const auto path = temp_path("ascii_" + std::to_string(degree) + ".ply");
    {
      std::ofstream f(path);
      f << "ply\nformat ascii 1.0\ncomment written by hand\nelement vertex 7\n";
      for (const auto& [name, values] : columns) f << "property double " << name << "\n";
      f << "end_header\n";
      f.precision(17);
      for (int64_t v = 0; v < 7; ++v) {
        for (const auto& [name, values] : columns) f << values[v].item<double>() << " ";
        f << "\n";
      }
    }
    auto loaded = load_gaussians_ply(path);
    ASSERT_TRUE(loaded.ok()) << loaded.status();
    EXPECT_EQ(loaded->max_sh_degree, degree);
    auto a = GaussianModel(m).parameters(), b = loaded->parameters();
    for (size_t i = 0; i < a.size(); ++i)
      EXPECT_TRUE(at::equal(*a[i], *b[i])) << "degree " << degree << ", parameter " << i;
    auto vertices = read_ply_vertices(path);
    ASSERT_TRUE(vertices.ok());
    EXPECT_TRUE(holds_gaussians(*vertices));
    std::filesystem::remove(path);
  }
}

TEST(GaussiansPly, APointCloudIsNoModelAndSHDegreesPadWithoutChangingTheRender) {
  const auto path = temp_path("cloud.ply");
  ASSERT_TRUE(write_point_cloud_ply({at::randn({5, 3}), at::rand({5, 3})}, path).ok());
  auto vertices = read_ply_vertices(path);
  ASSERT_TRUE(vertices.ok());
  EXPECT_FALSE(holds_gaussians(*vertices));
  std::filesystem::remove(path);

  const GaussianModel m = visible_model(200, 1);
  GaussianModel padded = with_sh_degree(m, 3);
  EXPECT_EQ(padded.sh_rest.size(1), 15);
  EXPECT_EQ(padded.max_sh_degree, 3);
  padded.sh_degree = 3;  // the added bands take part, as zeros
  EXPECT_TRUE(at::equal(render(m, front_camera()).rgb, render(padded, front_camera()).rgb));
  const GaussianModel dropped = with_sh_degree(padded, 0);
  EXPECT_EQ(dropped.sh_rest.size(1), 0);
  EXPECT_EQ(dropped.sh_degree, 0);
  EXPECT_TRUE(at::equal(dropped.sh_dc, m.sh_dc));
}

TEST(GaussiansPly, ErrorsNameTheFileAndProblem) {
  const auto path = temp_path("bad.ply");
  {
    std::ofstream f(path);
    f << "ply\nformat binary_little_endian 1.0\nelement vertex 10\nproperty float x\nend_header\n"
      << "abc";
  }
  auto r = load_gaussians_ply(path);
  ASSERT_FALSE(r.ok());
  EXPECT_NE(std::string(r.status().message()).find(path.string()), std::string::npos);
  // The count is checked against the bytes present before anything is read.
  EXPECT_NE(std::string(r.status().message()).find("announces 10 vertices"), std::string::npos) << r.status();
  auto missing = load_gaussians_ply(temp_path("does_not_exist.ply"));
  ASSERT_FALSE(missing.ok());
  EXPECT_NE(std::string(missing.status().message()).find("does_not_exist.ply"), std::string::npos);
  std::filesystem::remove(path);
}

TEST(PointCloudPly, RoundTrip) {
  PointCloud pc{at::randn({20, 3}), at::rand({20, 3})};
  const auto path = temp_path("points.ply");
  ASSERT_TRUE(write_point_cloud_ply(pc, path).ok());
  auto back = read_point_cloud_ply(path);
  ASSERT_TRUE(back.ok()) << back.status();
  EXPECT_TRUE(at::allclose(back->xyz, pc.xyz));
  EXPECT_TRUE(at::allclose(back->rgb, pc.rgb, 1e-5, 1e-6));
  std::filesystem::remove(path);
}

TEST(SphericalHarmonics, DegreeZeroIsTheDcColour) {
  const auto sh = rgb_to_sh_dc(at::tensor({0.2, 0.5, 0.9}, at::kDouble)).view({1, 1, 3});
  const auto c = sh_to_color(0, sh, at::tensor({0.0, 0.0, 1.0}, at::kDouble).view({1, 3}));
  EXPECT_TRUE(at::allclose(c, at::tensor({0.2, 0.5, 0.9}, at::kDouble).view({1, 3})));
}

TEST(SphericalHarmonics, DegreeOneFollowsTheBasis) {
  // Only the coefficient of -C1 * y is set: colour = 0.5 - C1 * y * k.
  auto sh = at::zeros({1, 4, 3}, at::kDouble);
  sh[0][1][0] = 1.0;
  const double y = 0.6;
  const auto dirs = at::tensor({0.0, y, 0.8}, at::kDouble).view({1, 3});
  const auto c = sh_to_color(1, sh, dirs);
  EXPECT_NEAR(c[0][0].item<double>(), 0.5 - 0.4886025119029199 * y, 1e-12);
  EXPECT_NEAR(c[0][1].item<double>(), 0.5, 1e-12);
}

TEST(SphericalHarmonics, GradientMatchesFiniteDifferences) {
  at::manual_seed(1);
  auto sh = at::randn({5, 16, 3}, at::kDouble) * 0.1;
  auto dirs = at::randn({5, 3}, at::kDouble);
  dirs = dirs / dirs.norm(2, {1}, true);
  auto w = at::randn({5, 3}, at::kDouble);
  sh.requires_grad_(true);
  (sh_to_color(3, sh, dirs) * w).sum().backward();
  const auto g = sh.grad();
  auto flat = sh.detach().view({-1});
  for (int64_t k = 0; k < flat.numel(); k += 7) {
    const double v = flat[k].item<double>(), eps = 1e-6;
    flat[k] = v + eps;
    const double up = (sh_to_color(3, sh.detach(), dirs) * w).sum().item<double>();
    flat[k] = v - eps;
    const double down = (sh_to_color(3, sh.detach(), dirs) * w).sum().item<double>();
    flat[k] = v;
    EXPECT_NEAR(g.view({-1})[k].item<double>(), (up - down) / (2 * eps), 1e-7) << "coefficient " << k;
  }
}

}  // namespace
}  // namespace gaps

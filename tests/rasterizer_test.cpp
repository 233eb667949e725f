// The rasterizer against a slow, readable reference renderer, and its analytic gradients against
// central finite differences (in double precision) for colour, depth and alpha outputs.
#include <algorithm>
#include <cmath>
#include <numeric>
#include <random>
#include <vector>

#include <ATen/ATen.h>
#include <gtest/gtest.h>
#include <Eigen/Dense>

#include "gs_trainer/raster/rasterize_backend.h"
#include "gs_trainer/raster/rasterizer.h"
#include "tests/raster_test_util.h"

namespace gaps {
namespace {

using test::RandomScene;

// Gaussians in front of a camera looking down +z from a slightly rotated pose. Opacities stay below
// 0.35 so that no Gaussian is cut off by its 3-sigma footprint while still above the 1/255 threshold:
// the rendered image is then a smooth function of every parameter and finite differences apply.
RandomScene make_scene(int n, int width, int height, at::ScalarType dtype, uint64_t seed) {
  at::manual_seed(seed);
  auto opts = at::TensorOptions().dtype(dtype);
  RandomScene s;
  s.means = at::rand({n, 3}, opts) * at::tensor({2.0, 1.6, 2.0}, opts) - at::tensor({1.0, 0.8, -2.0}, opts);
  s.quats = at::randn({n, 4}, opts);
  s.scales = at::rand({n, 3}, opts) * 0.25 + 0.05;
  s.opacities = at::rand({n}, opts) * 0.25 + 0.08;
  s.features = at::rand({n, 4}, opts);
  test::place_camera(s, width, height, opts);
  return s;
}

// Slow reference: per pixel, all Gaussians sorted by depth, everything recomputed from the definitions.
struct Reference {
  at::Tensor features, alpha;
};

Reference reference_render(const RandomScene& s) {
  const int n = static_cast<int>(s.means.size(0)), W = s.K.width, H = s.K.height;
  auto md = s.means.to(at::kDouble), qd = s.quats.to(at::kDouble), sd = s.scales.to(at::kDouble);
  auto vd = s.viewmat.to(at::kDouble), od = s.opacities.to(at::kDouble), fd = s.features.to(at::kDouble);
  Eigen::Matrix3d Wr;
  Eigen::Vector3d t;
  for (int r = 0; r < 3; ++r) {
    for (int c = 0; c < 3; ++c) Wr(r, c) = vd[r][c].item<double>();
    t(r) = vd[r][3].item<double>();
  }
  struct G2 {
    double z, mx, my;
    Eigen::Matrix2d conic;
    double radius;
  };
  std::vector<G2> gs(n);
  for (int i = 0; i < n; ++i) {
    Eigen::Vector3d mu(md[i][0].item<double>(), md[i][1].item<double>(), md[i][2].item<double>());
    Eigen::Quaterniond q(qd[i][0].item<double>(), qd[i][1].item<double>(), qd[i][2].item<double>(),
                         qd[i][3].item<double>());
    const Eigen::Matrix3d R = q.normalized().toRotationMatrix();
    const Eigen::Vector3d sc(sd[i][0].item<double>(), sd[i][1].item<double>(), sd[i][2].item<double>());
    const Eigen::Matrix3d M = R * sc.asDiagonal();
    const Eigen::Vector3d p = Wr * mu + t;
    Eigen::Matrix<double, 2, 3> J;
    J << s.K.fx / p.z(), 0, -s.K.fx * p.x() / (p.z() * p.z()), 0, s.K.fy / p.z(), -s.K.fy * p.y() / (p.z() * p.z());
    Eigen::Matrix2d cov = J * Wr * M * M.transpose() * Wr.transpose() * J.transpose();
    cov += 0.3 * Eigen::Matrix2d::Identity();
    const double mid = 0.5 * cov.trace(), det = cov.determinant();
    const double radius = std::ceil(3.0 * std::sqrt(mid + std::sqrt(std::max(0.1, mid * mid - det))));
    gs[i] = {p.z(), s.K.fx * p.x() / p.z() + s.K.cx, s.K.fy * p.y() / p.z() + s.K.cy, cov.inverse(), radius};
  }
  std::vector<int> order(n);
  std::iota(order.begin(), order.end(), 0);
  std::stable_sort(order.begin(), order.end(), [&](int a, int b) { return gs[a].z < gs[b].z; });
  const int C = static_cast<int>(fd.size(1));
  Reference ref{at::zeros({H, W, C}, at::kDouble), at::zeros({H, W}, at::kDouble)};
  for (int y = 0; y < H; ++y) {
    for (int x = 0; x < W; ++x) {
      double T = 1.0;
      std::vector<double> acc(C, 0.0);
      const Eigen::Vector2d pix(x + 0.5, y + 0.5);
      for (int i : order) {
        const Eigen::Vector2d d = Eigen::Vector2d(gs[i].mx, gs[i].my) - pix;
        if (std::abs(d.x()) > gs[i].radius + 16 || std::abs(d.y()) > gs[i].radius + 16) continue;
        const double power = -0.5 * d.dot(gs[i].conic * d);
        if (power > 0) continue;
        const double a = std::min(0.99, od[i].item<double>() * std::exp(power));
        if (a < 1.0 / 255.0) continue;
        if (T * (1 - a) < 1e-4) break;
        for (int c = 0; c < C; ++c) acc[c] += fd[i][c].item<double>() * a * T;
        T *= 1 - a;
      }
      for (int c = 0; c < C; ++c) ref.features[y][x][c] = acc[c];
      ref.alpha[y][x] = 1 - T;
    }
  }
  return ref;
}

RasterizedImage render(const RandomScene& s) {
  auto p = project_gaussians(s.means, s.quats, s.scales, s.viewmat, s.K);
  return rasterize_gaussians(p.means2d, p.conics, s.opacities, s.features, p.depths, p.radii, s.K.width, s.K.height);
}

TEST(Rasterizer, ForwardMatchesSlowReference) {
  const auto s = make_scene(60, 45, 37, at::kDouble, 7);
  const auto out = render(s);
  const auto ref = reference_render(s);
  EXPECT_GT(out.alpha.max().item<double>(), 0.3) << "scene should cover part of the image";
  EXPECT_LT((out.features - ref.features).abs().max().item<double>(), 1e-10);
  EXPECT_LT((out.alpha - ref.alpha).abs().max().item<double>(), 1e-10);
}

// Tiles are cut to where alpha can reach 1/255 (raster::tile_rect): faint and elongated Gaussians must
// still render exactly as the reference (which tests every Gaussian at every pixel), with far fewer
// (tile, Gaussian) pairs than their 3-sigma squares.
TEST(Rasterizer, OpacityAwareTilesLoseNoContribution) {
  auto s = make_scene(150, 64, 48, at::kDouble, 13);
  s.opacities = at::rand({150}, at::kDouble) * 0.05 + 0.0035;      // 0.9 to 13.6 times the 1/255 threshold
  s.scales = s.scales * at::tensor({1.0, 0.2, 0.6}, at::kDouble);  // elongated
  const auto out = render(s);
  const auto ref = reference_render(s);
  EXPECT_GT(out.alpha.max().item<double>(), 0.05) << "scene should show";
  EXPECT_LT((out.features - ref.features).abs().max().item<double>(), 1e-10);
  EXPECT_LT((out.alpha - ref.alpha).abs().max().item<double>(), 1e-10);
  const auto p = project_gaussians(s.means, s.quats, s.scales, s.viewmat, s.K);
  const auto faint = backend::bin_tiles_cpu(p.means2d, p.conics, s.opacities, p.radii, p.depths, 64, 48);
  const auto opaque =
      backend::bin_tiles_cpu(p.means2d, p.conics, at::full_like(s.opacities, 0.999), p.radii, p.depths, 64, 48);
  EXPECT_LT(faint.gaussian_ids.numel(), 0.8 * opaque.gaussian_ids.numel());  // 16-pixel tiles bound the gain here
}

TEST(Rasterizer, FloatMatchesDouble) {
  const auto sd = make_scene(200, 64, 48, at::kDouble, 11);
  RandomScene sf = sd;
  for (auto* t : {&sf.means, &sf.quats, &sf.scales, &sf.opacities, &sf.features, &sf.viewmat}) *t = t->to(at::kFloat);
  const auto a = render(sd), b = render(sf);
  EXPECT_LT((a.features - b.features.to(at::kDouble)).abs().max().item<double>(), 1e-4);
  EXPECT_LT((a.alpha - b.alpha.to(at::kDouble)).abs().max().item<double>(), 1e-4);
}

TEST(Rasterizer, CompositesFrontToBackAndStopsWhenOpaque) {
  auto opts = at::TensorOptions().dtype(at::kDouble);
  RandomScene s;
  s.means = at::tensor({0.0, 0.0, 2.0, 0.0, 0.0, 4.0, 0.0, 0.0, 6.0}, opts).view({3, 3});
  s.quats = at::tensor({1.0, 0.0, 0.0, 0.0}, opts).repeat({3, 1});
  s.scales = at::full({3, 3}, 1.0, opts);
  s.opacities = at::tensor({1.0, 0.5, 1.0}, opts);
  s.features = at::tensor({1.0, 0.0, 0.0, 2.0, 0.0, 1.0, 0.0, 4.0, 0.0, 0.0, 1.0, 6.0}, opts).view({3, 4});
  s.viewmat = at::eye(4, opts);
  s.K = {20, 20, 16.5, 16.5, 32, 32};  // every mean lands on the centre of pixel (16, 16)
  const auto out = render(s);
  // Front: alpha clamped to 0.99. Middle: alpha 0.5 with T = 0.01. Back: would take T to 5e-5 < 1e-4,
  // so compositing stops before it.
  EXPECT_NEAR(out.features[16][16][0].item<double>(), 0.99, 1e-12);
  EXPECT_NEAR(out.features[16][16][1].item<double>(), 0.005, 1e-12);
  EXPECT_NEAR(out.features[16][16][2].item<double>(), 0.0, 1e-12);
  EXPECT_NEAR(out.features[16][16][3].item<double>(), 2.0 * 0.99 + 4.0 * 0.005, 1e-12);
  EXPECT_NEAR(out.alpha[16][16].item<double>(), 1.0 - 0.01 * 0.5, 1e-12);
}

TEST(Rasterizer, CulledGaussiansBehindCameraHaveNoEffect) {
  auto s = make_scene(30, 32, 32, at::kDouble, 3);
  const auto before = render(s);
  auto extra = make_scene(5, 32, 32, at::kDouble, 4);
  extra.means.select(1, 2).fill_(-1.0);  // behind the camera
  s.means = at::cat({s.means, extra.means});
  s.quats = at::cat({s.quats, extra.quats});
  s.scales = at::cat({s.scales, extra.scales});
  s.opacities = at::cat({s.opacities, extra.opacities});
  s.features = at::cat({s.features, extra.features});
  const auto after = render(s);
  EXPECT_TRUE(at::allclose(before.features, after.features, 0, 0));
}

// Loss = <R1, features> + <R2, alpha> with fixed random weights, as a function of one parameter tensor.
double weighted_loss(const RandomScene& s, const at::Tensor& r1, const at::Tensor& r2) {
  const auto out = render(s);
  return ((out.features * r1).sum() + (out.alpha * r2).sum()).item<double>();
}

void check_gradient(RandomScene s, at::Tensor RandomScene::*param, const char* name) {
  const auto r1 = at::randn({s.K.height, s.K.width, 4}, at::kDouble);
  const auto r2 = at::randn({s.K.height, s.K.width}, at::kDouble);
  (s.*param).requires_grad_(true);
  const auto out = render(s);
  ((out.features * r1).sum() + (out.alpha * r2).sum()).backward();
  const at::Tensor analytic = (s.*param).grad().clone();
  (s.*param) = (s.*param).detach();
  const double eps = 1e-6;
  auto flat = (s.*param).view({-1});
  auto g = analytic.view({-1});
  double max_err = 0, max_ref = 0;
  for (int64_t k = 0; k < flat.numel(); ++k) {
    const double v = flat[k].item<double>();
    flat[k] = v + eps;
    const double up = weighted_loss(s, r1, r2);
    flat[k] = v - eps;
    const double down = weighted_loss(s, r1, r2);
    flat[k] = v;
    const double numeric = (up - down) / (2 * eps);
    max_err = std::max(max_err, std::abs(numeric - g[k].item<double>()));
    max_ref = std::max(max_ref, std::abs(numeric));
  }
  EXPECT_GT(max_ref, 1e-3) << name << ": gradient should not vanish";
  EXPECT_LT(max_err, 1e-5 * std::max(1.0, max_ref)) << name << " analytic vs finite differences";
}

TEST(RasterizerGradients, Means) {
  check_gradient(make_scene(12, 29, 23, at::kDouble, 5), &RandomScene::means, "means");
}
TEST(RasterizerGradients, Quats) {
  check_gradient(make_scene(12, 29, 23, at::kDouble, 5), &RandomScene::quats, "quats");
}
TEST(RasterizerGradients, Scales) {
  check_gradient(make_scene(12, 29, 23, at::kDouble, 5), &RandomScene::scales, "scales");
}
TEST(RasterizerGradients, Opacities) {
  check_gradient(make_scene(12, 29, 23, at::kDouble, 5), &RandomScene::opacities, "opacities");
}
TEST(RasterizerGradients, Features) {
  check_gradient(make_scene(12, 29, 23, at::kDouble, 5), &RandomScene::features, "features");
}

TEST(RasterizerGradients, AbsoluteMean2dGradientIsAccumulated) {
  auto s = make_scene(20, 32, 32, at::kDouble, 9);
  auto p = project_gaussians(s.means, s.quats, s.scales, s.viewmat, s.K);
  auto means2d = p.means2d.detach().requires_grad_(true);
  auto sink = at::zeros({20, 2}, at::kDouble);
  auto out = rasterize_gaussians(means2d, p.conics, s.opacities, s.features, p.depths, p.radii, 32, 32, sink);
  out.features.sum().backward();
  EXPECT_TRUE((sink >= means2d.grad().abs() - 1e-12).all().item<bool>());
  EXPECT_GT(sink.sum().item<double>(), 0.0);
}

}  // namespace
}  // namespace gaps

namespace gaps {
namespace {

// The compositing kernels skip a (pixel, Gaussian) pair whose exponent is below certain_skip_power(opacity) before
// computing any exponential: such a pair must be one eval_alpha rejects, in float (as the kernels compute) and in
// double, for opacities from faint to DropGaussian-scaled above 1.
TEST(Rasterizer, CertainSkipPowerOnlySkipsPairsEvalAlphaRejects) {
  std::mt19937 rng(7);
  std::uniform_real_distribution<double> log_opacity(std::log(1e-3), std::log(1.5)), offset(-2e-3, 2e-3);
  int skipped = 0, kept = 0;
  for (int i = 0; i < 200000; ++i) {
    const float opacity = static_cast<float>(std::exp(log_opacity(rng)));
    const float power = static_cast<float>(std::min(0.0, std::log(raster::kMinAlpha / opacity) + offset(rng)));
    if (power >= raster::certain_skip_power(opacity)) {
      ++kept;
      continue;
    }
    ++skipped;
    float alpha, gauss;
    double alpha_d, gauss_d;
    ASSERT_FALSE(raster::alpha_from_power_host_rounding(power, opacity, alpha, gauss))
        << "opacity " << opacity << " power " << power;
    ASSERT_FALSE(raster::alpha_from_power_host_rounding<double>(power, opacity, alpha_d, gauss_d))
        << "opacity " << opacity << " power " << power;
  }
  EXPECT_GT(skipped, 10000);
  EXPECT_GT(kept, 10000);
}

}  // namespace
}  // namespace gaps

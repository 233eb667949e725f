// The full render (SH colour, the paper's depth, alpha, background) and its gradients with respect to
// every raw model parameter, against central finite differences in double precision.
#include <cmath>
#include <stdexcept>

#include <ATen/ATen.h>
#include <gtest/gtest.h>
#include <Eigen/Geometry>

#include "gs_trainer/model/render.h"
#include "gs_trainer/raster/rasterizer.h"
#include "tests/raster_test_util.h"

namespace gaps {
namespace {

Camera test_camera(int w, int h) {
  Camera c;
  c.width = w;
  c.height = h;
  c.fx = c.fy = 0.9 * w;
  c.cx = 0.5 * w + 0.3;
  c.cy = 0.5 * h - 0.2;
  c.R = Eigen::AngleAxisd(0.15, Eigen::Vector3d(0.2, 1.0, -0.3).normalized()).toRotationMatrix();
  c.t = Eigen::Vector3d(0.1, -0.05, 0.2);
  return c;
}

using test::random_model;

TEST(Render, DepthIsAlphaWeightedDistanceFromTheCameraCentre) {
  auto o = at::TensorOptions().dtype(at::kDouble);
  GaussianModel m;
  m.max_sh_degree = 0;
  m.means = at::tensor({0.3, -0.2, 3.0}, o).view({1, 3});
  m.log_scales = at::full({1, 3}, std::log(0.5), o);
  m.quats = at::tensor({1.0, 0.0, 0.0, 0.0}, o).view({1, 4});
  m.opacity_logits = at::full({1}, 0.5, o);
  m.sh_dc = at::zeros({1, 1, 3}, o);
  m.sh_rest = at::zeros({1, 0, 3}, o);
  Camera c;
  c.width = c.height = 64;
  c.fx = c.fy = 50;
  c.cx = c.cy = 32;
  c.t = Eigen::Vector3d(0.0, 0.0, 0.5);  // centre at (0, 0, -0.5)
  const auto out = render(m, c);
  const double distance = std::sqrt(0.3 * 0.3 + 0.2 * 0.2 + 3.5 * 3.5);
  const auto ratio = out.depth / out.alpha.clamp_min(1e-12);
  const auto covered = out.alpha > 0.01;
  EXPECT_GT(covered.sum().item<int64_t>(), 10);
  EXPECT_LT((ratio.masked_select(covered) - distance).abs().max().item<double>(), 1e-9);
}

TEST(Render, BackgroundFillsWhatAlphaLeaves) {
  auto m = random_model(30, 2);
  const auto c = test_camera(40, 30);
  RenderOptions white;
  white.background = at::ones({3}, at::kDouble);
  const auto a = render(m, c), b = render(m, c, white);
  EXPECT_TRUE(at::allclose(b.rgb - a.rgb, (1 - a.alpha).unsqueeze(2).expand({30, 40, 3}), 1e-12, 1e-12));
}

// Each Gaussian's blending weights summed over the image, read off the backward pass, against the
// forward pass with one one-hot feature channel per Gaussian (channel k composites w_k at every pixel).
TEST(Render, BlendingWeightsEqualTheOneHotImagesSums) {
  const int n = 12;
  auto m = random_model(n, 5);
  m.means.select(1, 2).add_(-1.0);  // closer: overlapping footprints, occlusion matters
  const auto c = test_camera(40, 30);
  const at::Tensor weights = blending_weights(m, c);
  const raster::Intrinsics K{c.fx, c.fy, c.cx, c.cy, c.width, c.height};
  const auto proj = project_gaussians(m.means, m.quats, m.scales(), c.viewmat().to(at::kDouble), K);
  const auto one_hot = rasterize_gaussians(proj.means2d, proj.conics, m.opacities(), at::eye(n, at::kDouble),
                                           proj.depths, proj.radii, c.width, c.height);
  const at::Tensor expected = one_hot.features.sum(at::IntArrayRef{0, 1});
  ASSERT_EQ(weights.sizes(), expected.sizes());
  EXPECT_GT(expected.max().item<double>(), 10.0) << "the scene should cover part of the image";
  EXPECT_GT((expected < 1e-9).sum().item<int64_t>() + (expected > 1.0).sum().item<int64_t>(), n / 2);
  EXPECT_TRUE(at::allclose(weights, expected, 1e-9, 1e-9)) << weights << expected;
  EXPECT_FALSE(m.means.grad().defined()) << "the model must not receive gradients";
}

// render_views is render() without the graph: the same images bit for bit, views of two sizes in one call (the
// first two, of one size but not one focal length, share a stacked pass).
TEST(Render, ViewsEqualOneRenderPerCamera) {
  const auto m = random_model(40, 6);
  std::vector<Camera> cameras{test_camera(40, 30), test_camera(40, 30), test_camera(33, 21)};
  cameras[1].t = Eigen::Vector3d(-0.3, 0.1, 0.4);
  cameras[1].fx *= 1.1;
  cameras[1].cy += 0.7;
  const std::vector<RenderOutput> views = render_views(m, cameras);
  ASSERT_EQ(views.size(), cameras.size());
  for (size_t k = 0; k < cameras.size(); ++k) {
    const RenderOutput one = render(m, cameras[k]);
    EXPECT_GT(one.alpha.max().item<double>(), 0.1) << "view " << k << " should see Gaussians";
    EXPECT_TRUE(at::equal(views[k].rgb, one.rgb)) << "view " << k;
    EXPECT_TRUE(at::equal(views[k].depth, one.depth)) << "view " << k;
    EXPECT_TRUE(at::equal(views[k].alpha, one.alpha)) << "view " << k;
    EXPECT_FALSE(views[k].rgb.requires_grad());
  }
  EXPECT_TRUE(render_views(m, {}).empty());
  const RenderedViews stacked = render_same_size_views(m, {cameras[0], cameras[1]});
  EXPECT_EQ(stacked.rgb.sizes(), at::IntArrayRef({2, 30, 40, 3}));
  EXPECT_TRUE(at::equal(stacked.rgb[1], views[1].rgb));
  EXPECT_THROW(render_same_size_views(m, cameras), std::invalid_argument);
  EXPECT_THROW(render_same_size_views(m, {}), std::invalid_argument);
}

class RenderGradient : public ::testing::TestWithParam<int> {};

TEST_P(RenderGradient, MatchesFiniteDifferences) {
  const int param = GetParam();
  GaussianModel m = random_model(10, 5);
  const Camera c = test_camera(27, 21);
  RenderOptions opts;
  opts.background = at::tensor({0.2, 0.3, 0.4}, at::kDouble);
  const auto wr = at::randn({21, 27, 3}, at::kDouble), wd = at::randn({21, 27}, at::kDouble) * 0.1,
             wa = at::randn({21, 27}, at::kDouble);
  auto loss_of = [&](const GaussianModel& model) {
    const auto out = render(model, c, opts);
    return (out.rgb * wr).sum() + (out.depth * wd).sum() + (out.alpha * wa).sum();
  };
  at::Tensor& p = *m.parameters()[param];
  p.requires_grad_(true);
  loss_of(m).backward();
  const at::Tensor analytic = p.grad().clone();
  p = p.detach();
  auto flat = p.view({-1});
  double max_err = 0, max_ref = 0;
  const double eps = 1e-6;
  for (int64_t k = 0; k < flat.numel(); ++k) {
    const double v = flat[k].item<double>();
    flat[k] = v + eps;
    const double up = loss_of(m).item<double>();
    flat[k] = v - eps;
    const double down = loss_of(m).item<double>();
    flat[k] = v;
    const double numeric = (up - down) / (2 * eps);
    max_err = std::max(max_err, std::abs(numeric - analytic.view({-1})[k].item<double>()));
    max_ref = std::max(max_ref, std::abs(numeric));
  }
  EXPECT_GT(max_ref, 1e-4);
  EXPECT_LT(max_err, 1e-5 * std::max(1.0, max_ref));
}

// means, log_scales, quats, opacity_logits, sh_dc, sh_rest
INSTANTIATE_TEST_SUITE_P(EveryParameter, RenderGradient, ::testing::Range(0, 6));

}  // namespace
}  // namespace gaps

// The CUDA rasterizer against the CPU reference (which tests/rasterizer_test.cpp checks against a slow
// renderer and finite differences): projection, tile lists, compositing and every gradient, on random
// scenes and on LLFF fern. Every test skips without a CUDA device (or a build without the kernels).
//
// Tolerances. The kernels round every float operation like the CPU build (no FMA contraction) and take
// the CPU's alpha decisions (skip below 1/255, clamp at 0.99: alpha_from_power_host_rounding), so projections
// and tile lists match exactly and images to a few float ulps. What remains: the float exp of either side
// is only within ~2 ulp of the correctly rounded one, so transmittances can differ in their last bits, and
// in rare pixels (about one per 10^5 saturated pixels) that moves the "stop before T < 1e-4" decision by
// one Gaussian; gradients are float sums in another order (warp sums + atomics against per-tile sums).
// Hence: images within 1e-4 of the feature scale but for such rare pixels, gradients within 1e-3
// relative plus 1e-4 of the tensor's largest entry. Every comparison prints its figures ("[parity]").
#include <algorithm>
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <string>
#include <utility>
#include <vector>

#include <ATen/ATen.h>
#include <gtest/gtest.h>

#include "gs_trainer/gaps/candidate_renders.h"
#include "gs_trainer/gaps/scores.h"
#include "gs_trainer/model/gaussians.h"
#include "gs_trainer/model/render.h"
#include "gs_trainer/raster/rasterize_backend.h"
#include "gs_trainer/raster/rasterizer.h"
#include "gs_trainer/scene/scene.h"
#include "tests/gpu/require_cuda.h"
#include "tests/raster_test_util.h"

namespace gaps {
namespace {

const at::Device kCuda(at::kCUDA, 0);

// ---- comparisons ---------------------------------------------------------------------------------

// Checks |got - want| <= rel * |want| + abs_tol element-wise, except for at most `outliers` elements
// that must still be within outlier_tol, and prints the figures.
void expect_close(const std::string& what, const at::Tensor& got_in, const at::Tensor& want_in, double rel,
                  double abs_tol, int64_t outliers = 0, double outlier_tol = 0.0) {
  ASSERT_EQ(got_in.sizes(), want_in.sizes()) << what;
  const at::Tensor got = got_in.detach().cpu().to(at::kDouble), want = want_in.detach().cpu().to(at::kDouble);
  if (want.numel() == 0) return;
  const double scale = want.abs().max().item<double>();
  const at::Tensor diff = (got - want).abs();
  const double max_diff = diff.max().item<double>();
  const at::Tensor ratio = diff / (rel * want.abs() + std::max(abs_tol, 1e-300));
  const double worst = ratio.max().item<double>();
  const int64_t beyond = (ratio > 1.0).sum().item<int64_t>();
  const int64_t differing = (got != want).sum().item<int64_t>();
  std::printf("[parity] %-40s max|diff| %.3e  max|ref| %.3e  worst diff/tol %.3f  beyond tol %lld  differ %lld/%lld\n",
              what.c_str(), max_diff, scale, worst, static_cast<long long>(beyond), static_cast<long long>(differing),
              static_cast<long long>(want.numel()));
  EXPECT_LE(beyond, outliers) << what << ": max|diff| " << max_diff << " against max|ref| " << scale;
  if (outliers > 0) EXPECT_LE(max_diff, outlier_tol) << what;
}

double max_abs(const at::Tensor& t) { return t.numel() ? t.detach().abs().max().item<double>() : 0.0; }

// Images: within 1e-4 of the feature scale (1 for colours and alpha, the largest value for depths). The
// exception is the rare pixel where the last bits of the transmittance put the stop below T = 1e-4 one
// Gaussian earlier or later (see the top of the file): at most 1 in 10^4 pixels, and within 2e-2 of the
// scale (the stopping Gaussian carries at most alpha / (1 - alpha) * 1e-4 <= 1e-2 of the weight).
void expect_image_close(const std::string& what, const at::Tensor& got, const at::Tensor& want) {
  const double scale = std::max(1.0, max_abs(want));
  const int64_t pixels = want.size(0) * want.size(1);
  expect_close(what, got, want, 0.0, 1e-4 * scale, pixels / 10000, 2e-2 * scale);
}

// Gradients: 1e-3 relative plus 1e-4 of the tensor's largest entry.
void expect_grad_close(const std::string& what, const at::Tensor& got, const at::Tensor& want) {
  expect_close(what, got, want, 1e-3, 1e-4 * max_abs(want));
}

// ---- random scenes, seen by the camera of rasterizer_test.cpp -------------------------------------------

using test::RandomScene;

struct SceneSpec {
  int n, width, height, channels;
  double scale_lo, scale_hi, opacity_lo, opacity_hi;
  uint64_t seed;
};

// Gaussians 2 to 4 units in front of a slightly rotated camera. The small spec keeps opacities low and
// footprints small (as the finite-difference tests need); the wide one has large, overlapping, nearly
// opaque Gaussians, so alpha clamping, early termination and long tile lists are all exercised.
RandomScene make_scene(const SceneSpec& spec) {
  at::manual_seed(spec.seed);
  auto opts = at::TensorOptions().dtype(at::kDouble);
  RandomScene s;
  s.means = at::rand({spec.n, 3}, opts) * at::tensor({2.0, 1.6, 2.0}, opts) - at::tensor({1.0, 0.8, -2.0}, opts);
  s.quats = at::randn({spec.n, 4}, opts);
  s.scales = at::rand({spec.n, 3}, opts) * (spec.scale_hi - spec.scale_lo) + spec.scale_lo;
  s.opacities = at::rand({spec.n}, opts) * (spec.opacity_hi - spec.opacity_lo) + spec.opacity_lo;
  s.features = at::rand({spec.n, spec.channels}, opts);
  test::place_camera(s, spec.width, spec.height, opts);
  return s;
}

const SceneSpec kSmall{12, 29, 23, 4, 0.05, 0.30, 0.08, 0.33, 5};
const SceneSpec kWide{2000, 160, 120, 4, 0.02, 0.60, 0.05, 0.95, 17};

RandomScene to(const RandomScene& s, const at::Device& device, at::ScalarType dtype) {
  RandomScene out = s;
  for (auto* t : {&out.means, &out.quats, &out.scales, &out.opacities, &out.features, &out.viewmat})
    *t = t->detach().to(device, dtype, /*non_blocking=*/false, /*copy=*/true);  // fresh leaves
  return out;
}

// Everything a render and its backward produce, on the CPU in double for comparison.
struct SceneResult {
  at::Tensor features, alpha;
  std::vector<std::pair<std::string, at::Tensor>> grads;  // means, quats, scales, opacities, features, |mean2d|
};

// Loss = <R1, features> + <R2, alpha> with fixed random weights.
// Without the sink (with_sink = false) the |mean2d| sums are not asked for and not returned.
SceneResult render_with_grads(const RandomScene& scene, const at::Device& device, at::ScalarType dtype,
                              const at::Tensor& r1, const at::Tensor& r2, bool with_sink = true) {
  RandomScene s = to(scene, device, dtype);
  for (auto* t : {&s.means, &s.quats, &s.scales, &s.opacities, &s.features}) t->requires_grad_(true);
  const int64_t n = s.means.size(0);
  at::Tensor sink = with_sink ? at::zeros({n, 2}, s.means.options()) : at::Tensor();
  auto p = project_gaussians(s.means, s.quats, s.scales, s.viewmat, s.K);
  auto out =
      rasterize_gaussians(p.means2d, p.conics, s.opacities, s.features, p.depths, p.radii, s.K.width, s.K.height, sink);
  ((out.features * r1.to(device, dtype)).sum() + (out.alpha * r2.to(device, dtype)).sum()).backward();
  auto host = [](const at::Tensor& t) { return t.detach().cpu().to(at::kDouble); };
  SceneResult r{host(out.features), host(out.alpha), {}};
  r.grads = {{"means", host(s.means.grad())},
             {"quats", host(s.quats.grad())},
             {"scales", host(s.scales.grad())},
             {"opacities", host(s.opacities.grad())},
             {"features", host(s.features.grad())}};
  if (with_sink) r.grads.push_back({"means2d_abs (sink)", host(sink)});
  return r;
}

void compare_scene(const std::string& name, const SceneSpec& spec) {
  const RandomScene scene = make_scene(spec);
  at::manual_seed(spec.seed + 1);
  const auto r1 = at::randn({spec.height, spec.width, spec.channels}, at::kDouble);
  const auto r2 = at::randn({spec.height, spec.width}, at::kDouble);
  const SceneResult cpu = render_with_grads(scene, at::kCPU, at::kFloat, r1, r2);
  const SceneResult gpu = render_with_grads(scene, kCuda, at::kFloat, r1, r2);
  EXPECT_GT(cpu.alpha.max().item<double>(), 0.3) << name << ": the scene should cover part of the image";
  expect_image_close(name + " features", gpu.features, cpu.features);
  expect_image_close(name + " alpha", gpu.alpha, cpu.alpha);
  for (size_t i = 0; i < cpu.grads.size(); ++i) {
    EXPECT_GT(cpu.grads[i].second.abs().max().item<double>(), 0.0) << cpu.grads[i].first << " should not vanish";
    expect_grad_close(name + " d/" + cpu.grads[i].first, gpu.grads[i].second, cpu.grads[i].second);
  }
}

// ---- projection and tile lists, stage by stage --------------------------------------------------------
// The backend's CUDA entry points exist only in builds with the kernels; without them these tests are
// still registered (and skip), so every build lists the same GPU tests.

TEST(RasterizerCuda, ProjectionAndTileListsMatchCpuExactly) {
  GAPS_REQUIRE_CUDA_KERNELS();
#if defined(GAPS_CUDA_KERNELS)
  const RandomScene cpu = to(make_scene(kWide), at::kCPU, at::kFloat);
  const RandomScene gpu = to(cpu, kCuda, at::kFloat);
  const auto pc = backend::project_forward_cpu(cpu.means, cpu.quats, cpu.scales, cpu.viewmat, cpu.K);
  const auto pg = backend::project_forward_cuda(gpu.means, gpu.quats, gpu.scales, gpu.viewmat, gpu.K);
  EXPECT_TRUE(at::equal(pg.radii.cpu(), pc.radii)) << "radii";
  EXPECT_GT((pc.radii > 0).sum().item<int64_t>(), kWide.n / 2);
  expect_close("projection means2d", pg.means2d, pc.means2d, 1e-6, 1e-6);
  expect_close("projection conics", pg.conics, pc.conics, 1e-6, 1e-6 * max_abs(pc.conics));
  expect_close("projection depths", pg.depths, pc.depths, 1e-6, 1e-6);

  // Binning the same projection on both devices: identical lists, entry for entry.
  const auto bc =
      backend::bin_tiles_cpu(pc.means2d, pc.conics, cpu.opacities, pc.radii, pc.depths, cpu.K.width, cpu.K.height);
  const auto bg = backend::bin_tiles_cuda(pc.means2d.to(kCuda), pc.conics.to(kCuda), gpu.opacities, pc.radii.to(kCuda),
                                          pc.depths.to(kCuda), cpu.K.width, cpu.K.height);
  EXPECT_TRUE(at::equal(bg.gaussian_ids.cpu(), bc.gaussian_ids)) << "tile lists";
  const auto rg = bg.tile_ranges.cpu(), rc = bc.tile_ranges;
  const auto count_g = rg.select(1, 1) - rg.select(1, 0), count_c = rc.select(1, 1) - rc.select(1, 0);
  EXPECT_TRUE(at::equal(count_g, count_c)) << "entries per tile";
  const auto nonempty = count_c > 0;
  EXPECT_TRUE(at::equal(rg.select(1, 0).masked_select(nonempty), rc.select(1, 0).masked_select(nonempty)))
      << "tile range starts";
  std::printf("[parity] wide scene: %lld tile entries over %lld tiles, lists identical: %d\n",
              static_cast<long long>(bc.gaussian_ids.numel()), static_cast<long long>(rc.size(0)),
              static_cast<int>(at::equal(bg.gaussian_ids.cpu(), bc.gaussian_ids)));

  // Projection backward with the same upstream gradients.
  at::manual_seed(3);
  const auto gm = at::randn({kWide.n, 2}, at::kFloat), gc = at::randn({kWide.n, 3}, at::kFloat);
  const auto qc = backend::project_backward_cpu(cpu.means, cpu.quats, cpu.scales, cpu.viewmat, cpu.K, pc.radii, gm, gc);
  const auto qg = backend::project_backward_cuda(gpu.means, gpu.quats, gpu.scales, gpu.viewmat, gpu.K,
                                                 pc.radii.to(kCuda), gm.to(kCuda), gc.to(kCuda));
  expect_grad_close("projection d/means", qg.means, qc.means);
  expect_grad_close("projection d/quats", qg.quats, qc.quats);
  expect_grad_close("projection d/scales", qg.scales, qc.scales);
#endif  // GAPS_CUDA_KERNELS
}

// final_T and n_contrib are internal to the autograd function; compare them through the backend.
TEST(RasterizerCuda, CompositingStateMatchesCpu) {
  GAPS_REQUIRE_CUDA_KERNELS();
#if defined(GAPS_CUDA_KERNELS)
  const RandomScene cpu = to(make_scene(kWide), at::kCPU, at::kFloat);
  const RandomScene gpu = to(cpu, kCuda, at::kFloat);
  const int w = cpu.K.width, h = cpu.K.height;
  const auto pc = backend::project_forward_cpu(cpu.means, cpu.quats, cpu.scales, cpu.viewmat, cpu.K);
  const auto pg = backend::project_forward_cuda(gpu.means, gpu.quats, gpu.scales, gpu.viewmat, gpu.K);
  const auto bc = backend::bin_tiles_cpu(pc.means2d, pc.conics, cpu.opacities, pc.radii, pc.depths, w, h);
  const auto bg = backend::bin_tiles_cuda(pg.means2d, pg.conics, gpu.opacities, pg.radii, pg.depths, w, h);
  const auto oc = backend::rasterize_forward_cpu(bc, pc.means2d, pc.conics, cpu.opacities, cpu.features, w, h);
  const auto og = backend::rasterize_forward_cuda(bg, pg.means2d, pg.conics, gpu.opacities, gpu.features, w, h);
  expect_image_close("wide final_T", og.final_T, oc.final_T);
  const int64_t mismatched = (og.n_contrib.cpu() != oc.n_contrib).sum().item<int64_t>();
  const int64_t saturated = (oc.final_T < 1e-3).sum().item<int64_t>();
  std::printf("[parity] wide n_contrib: %lld of %d pixels differ (%lld pixels near saturation, max n_contrib %d)\n",
              static_cast<long long>(mismatched), w * h, static_cast<long long>(saturated),
              oc.n_contrib.max().item<int>());
  EXPECT_GT(saturated, 0) << "the wide scene should exercise early termination";
  // Only the rare ulp-level flips of the T < 1e-4 stop described at the top may differ.
  EXPECT_LE(mismatched, w * h / 1000);
#endif  // GAPS_CUDA_KERNELS
}

// ---- the public API: images and every gradient ---------------------------------------------------------

TEST(RasterizerCuda, SmallSceneMatchesCpu) {
  GAPS_REQUIRE_CUDA_KERNELS();
  compare_scene("small 12 @ 29x23", kSmall);
}

TEST(RasterizerCuda, WideSceneMatchesCpu) {
  GAPS_REQUIRE_CUDA_KERNELS();
  compare_scene("wide 2000 @ 160x120", kWide);
}

// Without a sink the CUDA backward runs its variant that never sums |mean2d|; here channel 3 also gets no
// output gradient and channel 0 none in the left half of the image. Every gradient must match the CPU's.
TEST(RasterizerCuda, ChannelsWithoutGradientAndNoSinkMatchCpu) {
  GAPS_REQUIRE_CUDA_KERNELS();
  const SceneSpec spec = kWide;
  const RandomScene scene = make_scene(spec);
  at::manual_seed(spec.seed + 2);
  at::Tensor r1 = at::randn({spec.height, spec.width, spec.channels}, at::kDouble);
  r1.select(2, 3).zero_();
  r1.select(2, 0).narrow(1, 0, spec.width / 2).zero_();
  const auto r2 = at::randn({spec.height, spec.width}, at::kDouble);
  const SceneResult cpu = render_with_grads(scene, at::kCPU, at::kFloat, r1, r2, /*with_sink=*/false);
  const SceneResult gpu = render_with_grads(scene, kCuda, at::kFloat, r1, r2, /*with_sink=*/false);
  ASSERT_EQ(cpu.grads.size(), gpu.grads.size());
  for (size_t i = 0; i < cpu.grads.size(); ++i)
    expect_grad_close("zero-gradient channels d/" + cpu.grads[i].first, gpu.grads[i].second, cpu.grads[i].second);
  const at::Tensor g_feat = gpu.grads[4].second;
  EXPECT_EQ(g_feat.select(1, 3).abs().max().item<double>(), 0.0) << "channel 3 had no output gradient";
  EXPECT_GT(g_feat.select(1, 0).abs().max().item<double>(), 0.0) << "channel 0 had some";
}

// More channels than the 4 that render() composites take the kernels' 16-channel variant.
TEST(RasterizerCuda, SevenChannelsMatchCpu) {
  GAPS_REQUIRE_CUDA_KERNELS();
  SceneSpec spec = kWide;
  spec.n = 500;
  spec.channels = 7;
  compare_scene("500 x 7 channels @ 160x120", spec);
}

// The CPU double-precision gradients are checked against finite differences in rasterizer_test.cpp;
// CUDA float against them checks the CUDA gradients transitively (float rounding of the whole pipeline,
// hence the looser tolerance).
TEST(RasterizerCuda, FloatGradientsMatchCpuDouble) {
  GAPS_REQUIRE_CUDA_KERNELS();
  const RandomScene scene = make_scene(kSmall);
  at::manual_seed(99);
  const auto r1 = at::randn({kSmall.height, kSmall.width, kSmall.channels}, at::kDouble);
  const auto r2 = at::randn({kSmall.height, kSmall.width}, at::kDouble);
  const SceneResult ref = render_with_grads(scene, at::kCPU, at::kDouble, r1, r2);
  const SceneResult gpu = render_with_grads(scene, kCuda, at::kFloat, r1, r2);
  expect_close("small features vs double", gpu.features, ref.features, 0.0, 1e-4);
  for (size_t i = 0; i < ref.grads.size(); ++i)
    expect_close("small d/" + ref.grads[i].first + " vs double", gpu.grads[i].second, ref.grads[i].second, 2e-3,
                 2e-3 * max_abs(ref.grads[i].second));
}

TEST(RasterizerCuda, ForwardIsDeterministic) {
  GAPS_REQUIRE_CUDA_KERNELS();
  const RandomScene s = to(make_scene(kWide), kCuda, at::kFloat);
  auto render_once = [&] {
    auto p = project_gaussians(s.means, s.quats, s.scales, s.viewmat, s.K);
    return rasterize_gaussians(p.means2d, p.conics, s.opacities, s.features, p.depths, p.radii, s.K.width, s.K.height);
  };
  const auto a = render_once(), b = render_once();
  EXPECT_TRUE(at::equal(a.features, b.features));
  EXPECT_TRUE(at::equal(a.alpha, b.alpha));
}

TEST(RasterizerCuda, NothingVisibleGivesEmptyImageAndZeroGradients) {
  GAPS_REQUIRE_CUDA_KERNELS();
  RandomScene s = to(make_scene(kSmall), kCuda, at::kFloat);
  s.means = s.means.clone();
  s.means.select(1, 2).fill_(-1.0);  // behind the camera
  s.means.requires_grad_(true);
  s.opacities.requires_grad_(true);
  auto p = project_gaussians(s.means, s.quats, s.scales, s.viewmat, s.K);
  auto out =
      rasterize_gaussians(p.means2d, p.conics, s.opacities, s.features, p.depths, p.radii, s.K.width, s.K.height);
  EXPECT_EQ(out.features.abs().max().item<float>(), 0.f);
  EXPECT_EQ(out.alpha.abs().max().item<float>(), 0.f);
  (out.features.sum() + out.alpha.sum()).backward();
  EXPECT_EQ(s.means.grad().abs().max().item<float>(), 0.f);
  EXPECT_EQ(s.opacities.grad().abs().max().item<float>(), 0.f);
}

TEST(RasterizerCuda, RejectsDoubleWithAClearError) {
  GAPS_REQUIRE_CUDA_KERNELS();
  const RandomScene s = to(make_scene(kSmall), kCuda, at::kDouble);
  try {
    project_gaussians(s.means, s.quats, s.scales, s.viewmat, s.K);
    FAIL() << "double CUDA tensors should be rejected";
  } catch (const c10::Error& e) {
    EXPECT_NE(std::string(e.what()).find("float32"), std::string::npos) << e.what();
  }
}

// ---- LLFF fern through render(): SH colour, depth, alpha and the raw model parameters ------------------

struct FernResult {
  at::Tensor rgb, depth, alpha;
  std::vector<std::pair<std::string, at::Tensor>> grads;
};

FernResult render_fern(const GaussianModel& cpu_model, const Camera& camera, const at::Device& device,
                       const at::Tensor& r_rgb, const at::Tensor& r_depth, const at::Tensor& r_alpha) {
  GaussianModel model = cpu_model.to(device);
  for (at::Tensor* p : model.parameters()) *p = p->detach().clone().requires_grad_(true);  // fresh leaves
  RenderOptions options;
  options.means2d_abs_sink = at::zeros({model.size(), 2}, model.means.options());
  const RenderOutput out = render(model, camera, options);
  ((out.rgb * r_rgb.to(device)).sum() + (out.depth * r_depth.to(device)).sum() + (out.alpha * r_alpha.to(device)).sum())
      .backward();
  auto host = [](const at::Tensor& t) { return t.detach().cpu().to(at::kDouble); };
  FernResult r{host(out.rgb), host(out.depth), host(out.alpha), {}};
  const char* names[] = {"means", "log_scales", "quats", "opacity_logits", "sh_dc", "sh_rest"};
  const auto params = model.parameters();
  for (size_t i = 0; i < params.size(); ++i) r.grads.push_back({names[i], host(params[i]->grad())});
  r.grads.push_back({"means2d_abs (sink)", host(options.means2d_abs_sink)});
  return r;
}

void compare_fern(const std::string& name, const GaussianModel& model, const Camera& camera) {
  at::manual_seed(21);
  const auto r_rgb = at::randn({camera.height, camera.width, 3});
  const auto r_depth = at::randn({camera.height, camera.width}) * 0.1;
  const auto r_alpha = at::randn({camera.height, camera.width});
  const FernResult cpu = render_fern(model, camera, at::kCPU, r_rgb, r_depth, r_alpha);
  const FernResult gpu = render_fern(model, camera, kCuda, r_rgb, r_depth, r_alpha);
  EXPECT_GT(cpu.alpha.mean().item<double>(), 0.2) << name << ": the Gaussians should cover the view";
  expect_image_close(name + " rgb", gpu.rgb, cpu.rgb);
  expect_image_close(name + " depth", gpu.depth, cpu.depth);
  expect_image_close(name + " alpha", gpu.alpha, cpu.alpha);
  for (size_t i = 0; i < cpu.grads.size(); ++i)
    expect_grad_close(name + " d/" + cpu.grads[i].first, gpu.grads[i].second, cpu.grads[i].second);
}

class RasterizerCudaFern : public ::testing::Test {
 protected:
  void SetUp() override {
    GAPS_REQUIRE_CUDA_KERNELS();
    const std::filesystem::path root = GAPS_DATA_DIR "/llff/fern";
    if (!std::filesystem::exists(root)) GTEST_SKIP() << "no LLFF fern under " << root;
    SceneLoadOptions load;
    load.resolution = 8;
    auto scene = load_scene(root, load);
    ASSERT_TRUE(scene.ok()) << scene.status();
    camera_ = scene->cameras[0];
    const double far = camera_.far > 0 ? camera_.far : 100.0;
    model_ = gaussians_from_points(random_points_in_views({camera_}, 20000, far, 0), 3);
    model_.sh_degree = 3;
    // Anisotropic, rotated Gaussians (the initialisation's are round, which leaves the rotation gradient
    // at rounding noise) and non-zero higher SH bands, so that every parameter has a real gradient.
    at::manual_seed(8);
    model_.log_scales = model_.log_scales + at::randn_like(model_.log_scales) * 0.4;
    model_.quats = at::randn_like(model_.quats);
    model_.sh_rest = at::randn_like(model_.sh_rest) * 0.05;
  }
  void expect_views_equal_one_render_per_camera(const GaussianModel& model) const;
  Camera camera_;
  GaussianModel model_;
};

TEST_F(RasterizerCudaFern, RandomInitialisationMatchesCpu) { compare_fern("fern 20k init", model_, camera_); }

// Nearly opaque Gaussians: most pixels saturate, so early termination and the alpha clamp dominate.
TEST_F(RasterizerCudaFern, OpaqueGaussiansMatchCpu) {
  at::manual_seed(9);
  model_.opacity_logits = at::rand_like(model_.opacity_logits) * 6.0 - 1.0;
  compare_fern("fern 20k opaque", model_, camera_);
}

// Scoring's batched renders (one host synchronisation for all views) give render()'s images bit for bit, and the
// pool's statistics those of one measurement per view; at every SH degree (the stacked shading is compiled per
// degree).
TEST_F(RasterizerCudaFern, ViewsAndCandidateStatisticsEqualOneRenderPerCamera) {
  for (int degree : {3, 0, 1, 2}) {
    SCOPED_TRACE(testing::Message() << "SH degree " << degree);
    GaussianModel model = model_.to(kCuda);
    model.sh_degree = degree;
    expect_views_equal_one_render_per_camera(model);
  }
}

void RasterizerCudaFern::expect_views_equal_one_render_per_camera(const GaussianModel& model) const {
  Camera moved = camera_, half = camera_;
  moved.t += Eigen::Vector3d(0.05, -0.02, 0.03);
  moved.fx *= 1.05;  // same size, other intrinsics: still one stacked pass
  moved.cx += 0.3;
  half.width /= 2;
  half.height /= 2;
  half.fx /= 2;
  half.fy /= 2;
  half.cx /= 2;
  half.cy /= 2;
  // The first three share one stacked pass.
  const std::vector<Camera> cameras{camera_, moved, camera_, half};
  const std::vector<RenderOutput> views = render_views(model, cameras);
  const GapsConfig c;
  const at::Tensor rows = candidate_statistics(model, cameras, c);
  for (size_t k = 0; k < cameras.size(); ++k) {
    const RenderOutput one = render(model, cameras[k]);
    EXPECT_TRUE(one.rgb.is_cuda());
    EXPECT_TRUE(at::equal(views[k].rgb, one.rgb)) << "view " << k;
    EXPECT_TRUE(at::equal(views[k].depth, one.depth)) << "view " << k;
    EXPECT_TRUE(at::equal(views[k].alpha, one.alpha)) << "view " << k;
    // Against the CPU's ATen definition of the statistics (the pool's are the fused kernel's).
    const CandidateMeasurements m = measure_render(one.rgb.cpu().clamp(0, 1), one.alpha.cpu(), 0, 0, std::nullopt, c);
    const int64_t i = static_cast<int64_t>(k);
    EXPECT_NEAR(rows[i][0].item<double>(), m.mean_alpha, 1e-9) << "view " << k;
    EXPECT_NEAR(rows[i][1].item<double>(), m.entropy_mean, 1e-6) << "view " << k;
    EXPECT_NEAR(rows[i][2].item<double>(), m.coverage, 1e-12) << "view " << k;
    EXPECT_NEAR(rows[i][3].item<double>(), m.contrast, 1e-9) << "view " << k;
  }
  EXPECT_GT(rows[0][0].item<double>(), 0.2) << "the Gaussians should cover the view";
}

}  // namespace
}  // namespace gaps

// The reproject pseudo-view backend on ray-cast synthetic scenes (exact references, so the warp can be
// compared with a directly computed view), on the real fern scene, and its input errors and registry.
#include "diffusion_worker/reproject_generator.h"

#include <ATen/ATen.h>
#include <ATen/Parallel.h>
#include <gtest/gtest.h>

#include <Eigen/Dense>
#include <Eigen/Geometry>
#include <algorithm>
#include <cmath>
#include <ctime>
#include <filesystem>
#include <functional>
#include <iostream>
#include <optional>
#include <string>
#include <vector>

#include "diffusion_worker/backend_registry.h"
#include "gs_trainer/scene/scene.h"
#include "tests/camera_test_util.h"

namespace gaps {
namespace {

using test::camera_looking_down_z;

constexpr double kPi = 3.14159265358979323846;

bool contains(const absl::Status& status, const std::string& text) {
  return status.message().find(text) != absl::string_view::npos;
}

// ---------------------------------------------------------------------------------------------------
// Ray-cast synthetic scenes. Cameras look down +z (R = identity) from a centre on the x axis.

struct Hit {
  Eigen::Vector3d color;
  double distance;  // along the unit ray
};
// Nearest surface along the unit ray direction from an origin.
using SceneFn = std::function<Hit(const Eigen::Vector3d& origin, const Eigen::Vector3d& dir)>;

// Smooth texture, period 1.6 world units (24 pixels at the test scale): linear resampling stays accurate.
Eigen::Vector3d plane_texture(double x, double y) {
  const double k = 2 * kPi / 1.6;
  return {0.5 + 0.35 * std::sin(k * x), 0.5 + 0.35 * std::cos(k * y), 0.5 + 0.3 * std::sin(k * (x + y))};
}

std::optional<double> hit_plane(const Eigen::Vector3d& o, const Eigen::Vector3d& d, double z) {
  const double s = (z - o.z()) / d.z();
  return s > 0 ? std::optional<double>(s) : std::nullopt;
}

// A fronto-parallel textured plane at z = 4.
SceneFn textured_plane() {
  return [](const Eigen::Vector3d& o, const Eigen::Vector3d& d) {
    const double s = *hit_plane(o, d, 4.0);
    const Eigen::Vector3d p = o + s * d;
    return Hit{plane_texture(p.x(), p.y()), s};
  };
}

const Eigen::Vector3d kSquareColor(0.9, 0.2, 0.1);
constexpr double kSquareZ = 2.0, kSquareHalf = 0.4;

bool hits_square(const Eigen::Vector3d& o, const Eigen::Vector3d& d, double* s_out = nullptr) {
  const double s = *hit_plane(o, d, kSquareZ);
  const Eigen::Vector3d p = o + s * d;
  if (s_out) *s_out = s;
  return std::abs(p.x()) < kSquareHalf && std::abs(p.y()) < kSquareHalf;
}

// A red square at z = 2 in front of a plane at z = 4 whose texture has no red at all.
SceneFn square_before_plane() {
  return [](const Eigen::Vector3d& o, const Eigen::Vector3d& d) {
    double s;
    if (hits_square(o, d, &s)) return Hit{kSquareColor, s};
    s = *hit_plane(o, d, 4.0);
    const Eigen::Vector3d p = o + s * d;
    const Eigen::Vector3d t = plane_texture(p.x(), p.y());
    return Hit{Eigen::Vector3d(0.0, t.y(), t.z()), s};
  };
}

Eigen::Vector3d pixel_ray(const Camera& c, int i, int j) {
  const Eigen::Vector3d cam((j + 0.5 - c.cx) / c.fx, (i + 0.5 - c.cy) / c.fy, 1.0);
  return (c.R.transpose() * cam).normalized();
}

// The exact view of the scene: image, depth = distance (alpha 1, so depth/alpha is the distance).
ReferenceView view_of(const Camera& camera, const SceneFn& scene) {
  ReferenceView v;
  v.camera = camera;
  v.image = at::zeros({camera.height, camera.width, 3}, at::kFloat);
  v.render_depth = at::zeros({camera.height, camera.width}, at::kFloat);
  v.render_alpha = at::ones({camera.height, camera.width}, at::kFloat);
  auto img = v.image.accessor<float, 3>();
  auto depth = v.render_depth.accessor<float, 2>();
  for (int i = 0; i < camera.height; ++i) {
    for (int j = 0; j < camera.width; ++j) {
      const Hit h = scene(camera.center(), pixel_ray(camera, i, j));
      for (int c = 0; c < 3; ++c) img[i][j][c] = static_cast<float>(h.color[c]);
      depth[i][j] = static_cast<float>(h.distance);
    }
  }
  return v;
}

// A request with no model coverage at all (render black, alpha 0): the output is warp + inpainting.
GenerationRequest empty_render_request(const Camera& camera, std::vector<ReferenceView> references,
                                       double strength = 0.5) {
  GenerationRequest q;
  q.camera = camera;
  q.render_rgb = at::zeros({camera.height, camera.width, 3}, at::kFloat);
  q.render_depth = at::zeros({camera.height, camera.width}, at::kFloat);
  q.render_alpha = at::zeros({camera.height, camera.width}, at::kFloat);
  q.strength = strength;
  q.references = std::move(references);
  return q;
}

at::Tensor column_index(int height, int width) {
  return at::arange(width, at::kLong).view({1, width}).expand({height, width});
}

float max_abs_diff(const at::Tensor& a, const at::Tensor& b, const at::Tensor& mask) {
  const at::Tensor d = (a - b).abs().amax(-1);
  return d.masked_select(mask).max().item<float>();
}

void expect_valid_image(const at::Tensor& image, int height, int width) {
  ASSERT_EQ(image.sizes(), at::IntArrayRef({height, width, 3}));
  EXPECT_EQ(image.scalar_type(), at::kFloat);
  EXPECT_TRUE(at::isfinite(image).all().item<bool>());
  EXPECT_GE(image.min().item<float>(), 0.0f);
  EXPECT_LE(image.max().item<float>(), 1.0f);
}

constexpr int kW = 80, kH = 60;
constexpr double kF = 60;  // 15 pixels per world unit on the z = 4 plane

// --- Geometry -------------------------------------------------------------------------------------------

// Moving the camera right by b shifts the z = 4 plane left by b * f / 4 = 7.3 pixels: pseudo pixel j sees
// reference column j + 7.3, so the 2x2 splat makes it the linear interpolation of columns j + 7 and j + 8,
// and pixels j >= 73 (beyond column 79) were never seen.
TEST(ReprojectGeneratorTest, SidewaysPlaneMatchesTheDirectViewAndInpaintsTheDisocclusion) {
  const double b = 7.3 * 4.0 / kF;
  const Camera ref_cam = camera_looking_down_z(kW, kH, kF, {0, 0, 0});
  const Camera pseudo = camera_looking_down_z(kW, kH, kF, {b, 0, 0});
  const ReferenceView direct = view_of(pseudo, textured_plane());

  ReprojectGenerator generator;
  absl::StatusOr<ReprojectResult> r =
      generator.generate_one(empty_render_request(pseudo, {view_of(ref_cam, textured_plane())}));
  ASSERT_TRUE(r.ok()) << r.status();

  const at::Tensor col = column_index(kH, kW);
  EXPECT_TRUE(at::equal(r->warp_covered, col <= 72)) << "columns 73.. are disoccluded, the rest covered";
  EXPECT_FALSE(r->render_covered.any().item<bool>());
  // Resampling: linear interpolation of a 24-pixel-period texture is off by at most ~0.003.
  EXPECT_LT(max_abs_diff(r->warped, direct.image, col <= 71), 0.01f);
  // M of eq:two_stage: the uncovered columns dilated by 15x15 (7 pixels each side).
  EXPECT_TRUE(at::equal(r->inpaint_mask, col >= 73 - 7));
  // Outside M the output is the warp, i.e. the direct view.
  EXPECT_LT(max_abs_diff(r->image, direct.image, ~r->inpaint_mask), 0.01f);
  // Inside M it is inpainted from the texture around it (whose values lie in [0.15, 0.85]), not left black.
  expect_valid_image(r->image, kH, kW);
  const at::Tensor hole = r->image.masked_select(r->inpaint_mask.unsqueeze(-1).expand({kH, kW, 3}));
  EXPECT_GT(hole.min().item<float>(), 0.1f);
  EXPECT_LT(hole.max().item<float>(), 0.9f);
}

// The square (z = 2) moves 18.6 pixels, the plane behind it (z = 4) 9.3: plane pixels seen left of the
// square in the reference land under it in the pseudo view (the z-buffer must keep the square), and plane
// pixels hidden behind it become visible to its right (uncovered, inpainted).
TEST(ReprojectGeneratorTest, NearSquareOccludesTheFarPlane) {
  const Camera ref_cam = camera_looking_down_z(kW, kH, kF, {0, 0, 0});
  const Camera pseudo = camera_looking_down_z(kW, kH, kF, {0.62, 0, 0});
  const ReferenceView direct = view_of(pseudo, square_before_plane());
  ReprojectGenerator generator;
  absl::StatusOr<ReprojectResult> r =
      generator.generate_one(empty_render_request(pseudo, {view_of(ref_cam, square_before_plane())}));
  ASSERT_TRUE(r.ok()) << r.status();
  expect_valid_image(r->image, kH, kW);

  // What the pseudo camera sees at each pixel, and whether the reference saw that point.
  auto square_at = [&](int i, int j) {
    return i >= 0 && i < kH && j >= 0 && j < kW && hits_square(pseudo.center(), pixel_ray(pseudo, i, j));
  };
  auto seen_by_reference = [&](int i, int j) {
    if (i < 0 || i >= kH || j < 0 || j >= kW) return true;
    const Eigen::Vector3d d = pixel_ray(pseudo, i, j);
    if (hits_square(pseudo.center(), d)) return true;
    const Eigen::Vector3d p = pseudo.center() + *hit_plane(pseudo.center(), d, 4.0) * d;
    const Eigen::Vector3d in_ref = ref_cam.R * p + ref_cam.t;
    const double u = ref_cam.fx * in_ref.x() / in_ref.z() + ref_cam.cx;
    const double v = ref_cam.fy * in_ref.y() / in_ref.z() + ref_cam.cy;
    const bool in_view = u >= 0 && u < ref_cam.width && v >= 0 && v < ref_cam.height;
    return in_view && !hits_square(ref_cam.center(), (p - ref_cam.center()).normalized());
  };
  int square_pixels = 0, disoccluded_pixels = 0, plane_pixels = 0;
  auto warped = r->warped.accessor<float, 3>();
  auto truth = direct.image.accessor<float, 3>();
  auto covered = r->warp_covered.accessor<bool, 2>();
  for (int i = 2; i < kH - 2; ++i) {
    for (int j = 2; j < kW - 2; ++j) {
      bool interior_square = true, interior_hidden = true, interior_seen = true;
      for (int di = -2; di <= 2; ++di) {
        for (int dj = -2; dj <= 2; ++dj) {
          interior_square &= square_at(i + di, j + dj);
          interior_hidden &= !seen_by_reference(i + di, j + dj);
          interior_seen &= seen_by_reference(i + di, j + dj) && !square_at(i + di, j + dj);
        }
      }
      if (interior_square) {
        ++square_pixels;
        ASSERT_TRUE(covered[i][j]);
        for (int c = 0; c < 3; ++c) ASSERT_NEAR(warped[i][j][c], kSquareColor[c], 1e-4) << i << "," << j;
      } else if (interior_hidden) {
        ++disoccluded_pixels;
        EXPECT_FALSE(covered[i][j]) << i << "," << j;
      } else if (interior_seen) {
        ++plane_pixels;
        for (int c = 0; c < 3; ++c) ASSERT_NEAR(warped[i][j][c], truth[i][j][c], 0.01) << i << "," << j;
      }
    }
  }
  // The square is 24 pixels wide; the disocclusion strip 9.3 pixels (5 after the 2-pixel margins), and
  // the image's right border (9.3 pixels) is disoccluded too.
  EXPECT_GT(square_pixels, 300);
  EXPECT_GT(disoccluded_pixels, 10);
  EXPECT_GT(plane_pixels, 1000);
  // The strip between square and plane is filled by inpainting.
  EXPECT_TRUE((r->inpaint_mask | r->warp_covered).all().item<bool>());
}

// Two references either side of the pseudo pose: each covers the border the other misses, and their blend
// is the direct view.
TEST(ReprojectGeneratorTest, TwoReferencesCoverEachOthersBorders) {
  const double b = 5.2 * 4.0 / kF;
  const Camera pseudo = camera_looking_down_z(kW, kH, kF, {0, 0, 0});
  const ReferenceView left = view_of(camera_looking_down_z(kW, kH, kF, {-b, 0, 0}), textured_plane());
  const ReferenceView right = view_of(camera_looking_down_z(kW, kH, kF, {b, 0, 0}), textured_plane());
  ReprojectGenerator generator;
  absl::StatusOr<ReprojectResult> r = generator.generate_one(empty_render_request(pseudo, {left, right}));
  ASSERT_TRUE(r.ok()) << r.status();
  EXPECT_TRUE(r->warp_covered.all().item<bool>());
  EXPECT_FALSE(r->inpaint_mask.any().item<bool>());
  const ReferenceView direct = view_of(pseudo, textured_plane());
  EXPECT_LT(max_abs_diff(r->image, direct.image, at::ones({kH, kW}, at::kBool)), 0.01f);

  // With num_references = 1 only the nearest (the first) is used, and its missing border is inpainted.
  ReprojectOptions one;
  one.num_references = 1;
  absl::StatusOr<ReprojectResult> r1 =
      ReprojectGenerator(one).generate_one(empty_render_request(pseudo, {left, right}));
  ASSERT_TRUE(r1.ok()) << r1.status();
  EXPECT_FALSE(r1->warp_covered.all().item<bool>());
}

// A reference at the pseudo pose itself outweighs one seeing the points ~7 degrees off (weight ratio
// (0.5 / 7.5)^2 < 0.5%), even when the other disagrees in colour.
TEST(ReprojectGeneratorTest, AReferenceAtThePseudoPoseDominatesTheBlend) {
  const Camera pseudo = camera_looking_down_z(kW, kH, kF, {0, 0, 0});
  const ReferenceView same = view_of(pseudo, textured_plane());
  ReferenceView other = view_of(camera_looking_down_z(kW, kH, kF, {0.49, 0, 0}), textured_plane());
  other.image = (other.image + 0.2).clamp(0, 1);
  ReprojectGenerator generator;
  absl::StatusOr<ReprojectResult> r = generator.generate_one(empty_render_request(pseudo, {other, same}));
  ASSERT_TRUE(r.ok()) << r.status();
  EXPECT_TRUE(r->warp_covered.all().item<bool>());
  EXPECT_LT(max_abs_diff(r->image, same.image, at::ones({kH, kW}, at::kBool)), 0.005f);
}

// --- Anchoring on the render ---------------------------------------------------------------------------

// Render: a flat colour, covered (alpha 1) except columns 0..9. Warp: covers columns 0..72 (as in the first
// test). So every pixel is covered by one or both; nothing is inpainted.
TEST(ReprojectGeneratorTest, StrengthAnchorsOnTheRender) {
  const double b = 7.3 * 4.0 / kF;
  const Camera pseudo = camera_looking_down_z(kW, kH, kF, {b, 0, 0});
  const ReferenceView ref = view_of(camera_looking_down_z(kW, kH, kF, {0, 0, 0}), textured_plane());
  const at::Tensor col = column_index(kH, kW);
  const at::Tensor render_covered = col >= 10;
  const at::Tensor flat = at::tensor({0.1f, 0.9f, 0.3f}).view({1, 1, 3}).expand({kH, kW, 3}).contiguous();

  auto run = [&](double strength) {
    GenerationRequest q = empty_render_request(pseudo, {ref}, strength);
    q.render_rgb = at::where(render_covered.unsqueeze(-1), flat, at::zeros_like(flat));
    q.render_alpha = render_covered.to(at::kFloat);
    q.render_depth = q.render_alpha * 4.0;
    absl::StatusOr<ReprojectResult> r = ReprojectGenerator().generate_one(q);
    EXPECT_TRUE(r.ok()) << r.status();
    EXPECT_TRUE(at::equal(r->render_covered, render_covered));
    EXPECT_FALSE(r->inpaint_mask.any().item<bool>());
    return *r;
  };
  const at::Tensor warp_covered = col <= 72;

  const ReprojectResult s0 = run(0.0);
  EXPECT_EQ(max_abs_diff(s0.image, flat, render_covered), 0.0f) << "sigma = 0 keeps the render";
  EXPECT_EQ(max_abs_diff(s0.image, s0.warped, ~render_covered), 0.0f) << "no render: the warp";

  const ReprojectResult s1 = run(1.0);
  EXPECT_EQ(max_abs_diff(s1.image, s1.warped, warp_covered), 0.0f) << "sigma = 1 takes the warp";
  EXPECT_EQ(max_abs_diff(s1.image, flat, ~warp_covered), 0.0f) << "no warp: the render";

  const ReprojectResult s3 = run(0.3);
  const at::Tensor mixed = 0.7 * flat + 0.3 * s3.warped;
  EXPECT_LT(max_abs_diff(s3.image, mixed, render_covered & warp_covered), 1e-6f);
}

// --- Batch, determinism, errors ------------------------------------------------------------------------

TEST(ReprojectGeneratorTest, GenerateIsDeterministicAndInRequestOrder) {
  const Camera ref_cam = camera_looking_down_z(kW, kH, kF, {0, 0, 0});
  const ReferenceView ref = view_of(ref_cam, square_before_plane());
  std::vector<GenerationRequest> requests;
  for (double x : {0.31, -0.2, 0.1}) {
    requests.push_back(empty_render_request(camera_looking_down_z(kW, kH, kF, {x, 0.05, 0}), {ref}));
    requests.back().seed = 7;
  }
  ReprojectGenerator generator;
  EXPECT_EQ(generator.name(), "reproject 1");
  absl::StatusOr<std::vector<at::Tensor>> a = generator.generate(requests);
  absl::StatusOr<std::vector<at::Tensor>> b = generator.generate(requests);
  ASSERT_TRUE(a.ok()) << a.status();
  ASSERT_TRUE(b.ok()) << b.status();
  ASSERT_EQ(a->size(), 3u);
  for (size_t i = 0; i < requests.size(); ++i) {
    EXPECT_TRUE(at::equal((*a)[i], (*b)[i]));
    EXPECT_TRUE(at::equal((*a)[i], generator.generate_one(requests[i])->image)) << i;
  }
  EXPECT_FALSE(at::equal((*a)[0], (*a)[1]));
}

TEST(ReprojectGeneratorTest, RejectsBadInputsNamingTheProblem) {
  const Camera cam = camera_looking_down_z(kW, kH, kF, {0, 0, 0});
  const ReferenceView ref = view_of(cam, textured_plane());
  ReprojectGenerator generator;
  auto expect_error = [&](GenerationRequest q, const std::vector<std::string>& words) {
    absl::StatusOr<std::vector<at::Tensor>> r = generator.generate({empty_render_request(cam, {ref}), std::move(q)});
    ASSERT_FALSE(r.ok());
    EXPECT_EQ(r.status().code(), absl::StatusCode::kInvalidArgument);
    for (const std::string& w : words) EXPECT_TRUE(contains(r.status(), w)) << r.status() << " lacks " << w;
  };
  GenerationRequest q = empty_render_request(cam, {ref});
  q.render_depth = at::zeros({kH, kW + 1});
  expect_error(q, {"request 1", "render_depth", "60x81", "60x80"});

  q = empty_render_request(cam, {ref});
  q.references[0].image = at::zeros({kH / 2, kW / 2, 3});
  expect_error(q, {"request 1 reference 0 image", "30x40x3"});

  q = empty_render_request(cam, {});
  expect_error(q, {"request 1", "no references"});

  q = empty_render_request(cam, {ref});
  q.references[0].render_depth = q.references[0].render_depth.clone();
  q.references[0].render_depth[3][4] = NAN;
  expect_error(q, {"request 1 reference 0 render_depth", "NaN"});

  q = empty_render_request(cam, {ref}, 1.5);
  expect_error(q, {"strength 1.5"});

  q = empty_render_request(cam, {ref});
  q.render_alpha = q.render_alpha - 1;
  expect_error(q, {"render_alpha", "outside [0, 1]"});

  // A reference that several requests carry is checked once, named after the first request that uses it; the
  // first problem in request order is the one reported.
  q = empty_render_request(cam, {ref});
  q.references[0].render_alpha = q.references[0].render_alpha + 2;
  GenerationRequest late = empty_render_request(cam, {ref}, 1.5);
  absl::StatusOr<std::vector<at::Tensor>> shared = generator.generate({empty_render_request(cam, {ref}), q, q, late});
  ASSERT_FALSE(shared.ok());
  EXPECT_TRUE(contains(shared.status(), "request 1 reference 0 render_alpha")) << shared.status();
  EXPECT_FALSE(contains(shared.status(), "strength")) << shared.status();

  // adapt() learns nothing but checks the views.
  EXPECT_TRUE(generator.adapt({ref, ref}, std::nullopt).ok());
  EXPECT_FALSE(generator.adapt({}, std::nullopt).ok());
  ReferenceView bad = ref;
  bad.render_alpha = at::full({kH, kW}, NAN);
  const absl::Status s = generator.adapt({ref, bad}, std::nullopt);
  EXPECT_TRUE(contains(s, "view 1 render_alpha")) << s;
}

// The backend has neither LoRA nor an IP-Adapter: asked for either, it says so instead of ignoring it.
TEST(ReprojectGeneratorTest, ControlsItCannotHonourAreNoted) {
  const Camera ref_cam = camera_looking_down_z(kW, kH, kF, {0, 0, 0});
  const ReferenceView ref = view_of(ref_cam, square_before_plane());
  ReprojectGenerator generator;
  ASSERT_TRUE(generator.adapt({ref}, SceneAdaptation{4, 50}).ok());
  EXPECT_EQ(
      generator.notes(),
      std::vector<std::string>{"reproject has no model to adapt: the 50 LoRA steps (rank 4) asked for were not run"});
  for (const std::optional<SceneAdaptation>& nothing_asked :
       {std::optional<SceneAdaptation>(SceneAdaptation{4, 0}), std::optional<SceneAdaptation>()}) {
    ASSERT_TRUE(generator.adapt({ref}, nothing_asked).ok());
    EXPECT_TRUE(generator.notes().empty());
  }

  GenerationRequest plain = empty_render_request(camera_looking_down_z(kW, kH, kF, {0.1, 0, 0}), {ref});
  GenerationRequest asking = plain;
  asking.ip_adapter_scale = 0.5;
  absl::StatusOr<std::vector<at::Tensor>> images = generator.generate({asking, plain});
  ASSERT_TRUE(images.ok()) << images.status();
  EXPECT_TRUE(at::equal((*images)[0], (*images)[1]));
  EXPECT_EQ(generator.notes(), std::vector<std::string>{"reproject has no IP-Adapter: 1/2 requests asked for "
                                                        "ip_adapter_scale 0.5, generated without an image prompt"});
  ASSERT_TRUE(generator.generate({plain}).ok());
  EXPECT_TRUE(generator.notes().empty());
}

TEST(ReprojectGeneratorTest, RegistryBuildsBackendsByName) {
  absl::StatusOr<std::unique_ptr<Generator>> g = make_generator("reproject", "");
  ASSERT_TRUE(g.ok()) << g.status();
  EXPECT_EQ((*g)->name(), "reproject 1");

  g = make_generator("reproject", R"({"splat_footprint": 1, "inpaint_radius": 5, "num_references": 3})");
  ASSERT_TRUE(g.ok()) << g.status();
  const auto* reproject = dynamic_cast<const ReprojectGenerator*>(g->get());
  ASSERT_NE(reproject, nullptr);
  EXPECT_EQ(reproject->options().splat_footprint, 1);
  EXPECT_EQ(reproject->options().inpaint_radius, 5.0);
  EXPECT_EQ(reproject->options().num_references, 3);
  EXPECT_EQ(reproject->options().inpaint_dilation, 15);

  g = make_generator("flux", "");
  ASSERT_FALSE(g.ok());
  EXPECT_TRUE(contains(g.status(), "'flux'")) << g.status();
  EXPECT_TRUE(contains(g.status(), "known: reproject, restore, sdxl")) << g.status();

  EXPECT_TRUE(
      contains(make_generator("reproject", R"({"footprint": 2})").status(), "unknown reproject option 'footprint'"));
  EXPECT_TRUE(contains(make_generator("reproject", R"({"splat_footprint": 1.5})").status(), "integer"));
  EXPECT_TRUE(contains(make_generator("reproject", R"({"inpaint_dilation": 14})").status(), "odd"));
  EXPECT_TRUE(contains(make_generator("reproject", "{not json").status(), "JSON object"));
}

// --- Real scene ------------------------------------------------------------------------------------------

ReferenceView fern_reference(const Camera& camera, float distance) {
  absl::StatusOr<at::Tensor> image = load_camera_image(camera);
  EXPECT_TRUE(image.ok()) << image.status();
  ReferenceView v;
  v.camera = camera;
  v.image = *image;
  v.render_alpha = at::ones({camera.height, camera.width}, at::kFloat);
  v.render_depth = at::full({camera.height, camera.width}, distance, at::kFloat);
  return v;
}

double median(std::vector<double> v) {
  std::sort(v.begin(), v.end());
  return v[v.size() / 2];
}

Camera midway(const Camera& a, const Camera& b) {
  Camera c = a;
  c.name = "pseudo";
  const Eigen::Quaterniond q = Eigen::Quaterniond(a.R).slerp(0.5, Eigen::Quaterniond(b.R));
  c.R = q.toRotationMatrix();
  c.t = -c.R * (0.5 * (a.center() + b.center()));
  return c;
}

// Fern at -r 8, with its cameras' median near and far bounds (the test skips without the benchmark data).
class ReprojectGeneratorFernTest : public ::testing::Test {
 protected:
  void SetUp() override {
    const std::filesystem::path root = std::filesystem::path(GAPS_DATA_DIR) / "llff" / "fern";
    if (!std::filesystem::exists(root)) GTEST_SKIP() << "benchmark data not found at " << root;
    SceneLoadOptions load;
    load.resolution = 8;
    absl::StatusOr<Scene> scene = load_scene(root, load);
    ASSERT_TRUE(scene.ok()) << scene.status();
    ASSERT_GT(scene->cameras.size(), 10u);
    std::vector<double> nears, fars;
    for (const Camera& c : scene->cameras) {
      nears.push_back(c.near);
      fars.push_back(c.far);
    }
    near_ = median(nears);
    far_ = median(fars);
    cameras_ = scene->cameras;
  }

  std::vector<Camera> cameras_;
  double near_ = 0, far_ = 0;
};

TEST_F(ReprojectGeneratorFernTest, ViewsWarpToAMidwayPoseAndReproduceThemselves) {
  // A plane-like constant distance: halfway between the scene's median near and far bounds.
  const float distance = static_cast<float>(0.5 * (near_ + far_));
  const Camera& cam1 = cameras_[1];
  const Camera& cam10 = cameras_[10];
  const ReferenceView ref1 = fern_reference(cam1, distance);
  const ReferenceView ref10 = fern_reference(cam10, distance);

  ReprojectGenerator generator;
  ASSERT_TRUE(generator.adapt({ref1, ref10}, std::nullopt).ok());
  const Camera pseudo = midway(cam1, cam10);
  absl::StatusOr<ReprojectResult> mid = generator.generate_one(empty_render_request(pseudo, {ref1, ref10}));
  ASSERT_TRUE(mid.ok()) << mid.status();
  expect_valid_image(mid->image, cam1.height, cam1.width);
  const double covered = mid->warp_covered.to(at::kFloat).mean().item<double>();
  std::cout << "fern " << cam1.width << "x" << cam1.height << ", distance " << distance << ", midway coverage "
            << covered << "\n";
  EXPECT_GT(covered, 0.8);

  // The identity pose with the view's own depth. Only reference 1: reference 10's constant-distance
  // sphere is a different surface, nearer in places, and the z-buffer would rightly prefer it there.
  absl::StatusOr<ReprojectResult> same = generator.generate_one(empty_render_request(cam1, {ref1}));
  ASSERT_TRUE(same.ok()) << same.status();
  expect_valid_image(same->image, cam1.height, cam1.width);
  const at::Tensor mask = same->warp_covered.unsqueeze(-1).expand_as(same->image);
  const double mse = (same->image - ref1.image).pow(2).masked_select(mask).mean().item<double>();
  const double psnr = 10 * std::log10(1.0 / std::max(mse, 1e-12));
  std::cout << "identity PSNR " << psnr << " dB on " << same->warp_covered.to(at::kFloat).mean().item<double>()
            << " of the pixels\n";
  EXPECT_GT(psnr, 30.0);
}

// The compact hand-over sends depth maps in half precision (rpc/codec.h): on fern's views with a varying depth
// (a slanted, rippled surface between the scene's bounds), the warp to a midway pose from the rounded depths is the
// warp from the exact ones (measured: 99.7 % of the pixels within a byte, 44.6 dB apart).
TEST_F(ReprojectGeneratorFernTest, HalfPrecisionDepthsWarpAsTheExactOnesDo) {
  const double near = near_, far = far_;
  const auto varying = [&](const Camera& camera) {
    ReferenceView v = fern_reference(camera, 1.0f);
    const at::Tensor x = at::linspace(0, 1, camera.width).unsqueeze(0);
    const at::Tensor y = at::linspace(0, 1, camera.height).unsqueeze(1);
    const at::Tensor t = 0.5 * (x + y) + 0.1 * at::sin(25 * x) * at::cos(17 * y);
    v.render_depth = (near + (far - near) * (0.2 + 0.6 * t)).to(at::kFloat).contiguous();
    return v;
  };
  const auto halves = [](ReferenceView v) {
    v.render_depth = v.render_depth.to(at::kHalf).to(at::kFloat);
    return v;
  };
  const Camera& cam1 = cameras_[1];
  const Camera& cam10 = cameras_[10];
  const std::vector<ReferenceView> exact = {varying(cam1), varying(cam10)};
  const std::vector<ReferenceView> rounded = {halves(exact[0]), halves(exact[1])};
  ASSERT_FALSE(at::equal(exact[0].render_depth, rounded[0].render_depth));  // the rounding changes the depths

  ReprojectGenerator generator;
  ASSERT_TRUE(generator.adapt(exact, std::nullopt).ok());
  const Camera pseudo = midway(cam1, cam10);
  absl::StatusOr<ReprojectResult> from_exact = generator.generate_one(empty_render_request(pseudo, exact));
  absl::StatusOr<ReprojectResult> from_halves = generator.generate_one(empty_render_request(pseudo, rounded));
  ASSERT_TRUE(from_exact.ok()) << from_exact.status();
  ASSERT_TRUE(from_halves.ok()) << from_halves.status();
  EXPECT_GT(from_exact->warp_covered.to(at::kFloat).mean().item<double>(), 0.5);
  const at::Tensor difference = (from_exact->image - from_halves->image).abs();
  const double mse = difference.pow(2).mean().item<double>();
  const double psnr = 10 * std::log10(1.0 / std::max(mse, 1e-12));
  const double within_byte = difference.le(1.0 / 255).all(-1).to(at::kFloat).mean().item<double>();
  std::cout << "half-precision depths: warp PSNR " << psnr << " dB against the exact depths', mean |difference| "
            << difference.mean().item<double>() * 255 << " / 255, max " << difference.max().item<double>() * 255
            << " / 255, pixels within 1/255: " << within_byte << "\n";
  // A few pixels where two surfaces lie within half precision of each other may swap in the z-buffer.
  EXPECT_GT(psnr, 40.0);
  EXPECT_GE(within_byte, 0.99);
  EXPECT_LT(difference.mean().item<double>(), 0.25 / 255);
}

}  // namespace
}  // namespace gaps

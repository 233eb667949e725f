// The restore pseudo-view backend (diffusion_worker/restore_generator.h): blurred renders of a fern photograph
// restored towards the photograph with the real Real-ESRGAN weights (LPIPS, PSNR, sharpness); its composition with
// reproject's warp on a ray-cast plane (random weights, so the real ones are not needed); its options' and requests'
// errors, the missing weights file, and the registry.
#include "diffusion_worker/restore_generator.h"

#include <ATen/ATen.h>
#include <gtest/gtest.h>
#include <stdlib.h>

#include <Eigen/Dense>
#include <cmath>
#include <filesystem>
#include <iostream>
#include <string>
#include <vector>

#include "diffusion_worker/backend_registry.h"
#include "diffusion_worker/restore/realesrgan_weights.h"
#include "gs_trainer/eval/lpips.h"
#include "tests/camera_test_util.h"
#include "tests/restore_test_util.h"
#include "tests/test_util.h"

namespace gaps {
namespace {

using test::camera_looking_down_z;
using test::contains;

// A fronto-parallel plane at z = 4 with a smooth colour texture, seen exactly (alpha 1, depth = distance).
ReferenceView plane_view(const Camera& camera) {
  ReferenceView v;
  v.camera = camera;
  v.image = at::zeros({camera.height, camera.width, 3});
  v.render_depth = at::zeros({camera.height, camera.width});
  v.render_alpha = at::ones({camera.height, camera.width});
  auto image = v.image.accessor<float, 3>();
  auto depth = v.render_depth.accessor<float, 2>();
  const Eigen::Vector3d o = camera.center();
  for (int i = 0; i < camera.height; ++i) {
    for (int j = 0; j < camera.width; ++j) {
      const Eigen::Vector3d d =
          Eigen::Vector3d((j + 0.5 - camera.cx) / camera.fx, (i + 0.5 - camera.cy) / camera.fy, 1).normalized();
      const double s = (4.0 - o.z()) / d.z();
      const Eigen::Vector3d p = o + s * d;
      image[i][j][0] = static_cast<float>(0.5 + 0.35 * std::sin(3.9 * p.x()));
      image[i][j][1] = static_cast<float>(0.5 + 0.35 * std::cos(3.9 * p.y()));
      image[i][j][2] = static_cast<float>(0.5 + 0.3 * std::sin(3.9 * (p.x() + p.y())));
      depth[i][j] = static_cast<float>(s);
    }
  }
  return v;
}

GenerationRequest render_request(const at::Tensor& render, const Camera& camera) {
  GenerationRequest q;
  q.camera = camera;
  q.render_rgb = render;
  q.render_depth = at::ones({camera.height, camera.width});
  q.render_alpha = at::ones({camera.height, camera.width});
  q.strength = 0.5;
  return q;
}

// The shrink-and-bilinear-enlarge blur of an image (the compose test's render).
at::Tensor blurred(const at::Tensor& image) {
  const at::Tensor chw = image.permute({2, 0, 1}).unsqueeze(0);
  const at::Tensor small = at::avg_pool2d(chw, 4);
  return at::upsample_bilinear2d(small, {image.size(0), image.size(1)}, false)
      .squeeze(0)
      .permute({1, 2, 0})
      .contiguous();
}

// A Gaussian blur of standard deviation sigma pixels (reflected borders): what an under-resolved render looks like.
at::Tensor gaussian_blurred(const at::Tensor& image, double sigma) {
  const int64_t radius = static_cast<int64_t>(std::ceil(3 * sigma));
  at::Tensor kernel = at::arange(-radius, radius + 1, at::kFloat).pow(2).div(-2 * sigma * sigma).exp();
  kernel = kernel / kernel.sum();
  at::Tensor x = image.permute({2, 0, 1}).unsqueeze(1);  // 3 x 1 x H x W
  x = at::reflection_pad2d(x, {radius, radius, radius, radius});
  x = at::conv2d(x, kernel.view({1, 1, 1, -1}));
  x = at::conv2d(x, kernel.view({1, 1, -1, 1}));
  return x.squeeze(1).permute({1, 2, 0}).contiguous();
}

double psnr(const at::Tensor& a, const at::Tensor& b) {
  return 10 * std::log10(1.0 / (a - b).pow(2).mean().item<double>());
}

// Sharpness: the mean magnitude of horizontal differences, which blur removes.
double detail(const at::Tensor& t) { return (t.slice(1, 1) - t.slice(1, 0, -1)).abs().mean().item<double>(); }

struct FernRestoration {
  at::Tensor sharp, render, image;
  double lpips_blurred = 0, lpips_restored = 0;
};

// A crop of a fern photograph blurred by sigma, restored by the backend with `options`; LPIPS of both to the
// photograph.
void restore_fern(int64_t top, int64_t left, int64_t height, int64_t width, double sigma, const std::string& options,
                  FernRestoration* out) {
  const std::filesystem::path lpips_weights = default_lpips_weights_path();
  ASSERT_TRUE(std::filesystem::is_regular_file(lpips_weights))
      << "LPIPS weights missing at " << lpips_weights << ": bash scripts/setup.sh makes them";
  out->sharp = test::fern_crop(top, left, height, width);
  ASSERT_TRUE(out->sharp.defined());
  out->render = gaussian_blurred(out->sharp, sigma);
  const Camera camera = camera_looking_down_z(static_cast<int>(width), static_cast<int>(height), 100, {0, 0, 0});
  absl::StatusOr<std::unique_ptr<Generator>> generator = make_generator("restore", options);
  ASSERT_TRUE(generator.ok()) << generator.status();
  absl::StatusOr<std::vector<at::Tensor>> images = (*generator)->generate({render_request(out->render, camera)});
  ASSERT_TRUE(images.ok()) << images.status();
  ASSERT_EQ(images->size(), 1u);
  out->image = images->front();
  ASSERT_EQ(out->image.sizes(), at::IntArrayRef({height, width, 3}));
  EXPECT_EQ(out->image.scalar_type(), at::kFloat);
  EXPECT_TRUE(out->image.device().is_cpu());
  EXPECT_GE(out->image.min().item<float>(), 0.0f);
  EXPECT_LE(out->image.max().item<float>(), 1.0f);
  EXPECT_TRUE((*generator)->notes().empty());

  absl::StatusOr<Lpips> lpips = Lpips::load_safetensors(lpips_weights.string());
  ASSERT_TRUE(lpips.ok()) << lpips.status();
  out->lpips_restored = lpips->distance(out->image, out->sharp).item<double>();
  out->lpips_blurred = lpips->distance(out->render, out->sharp).item<double>();
  std::cout << "fern " << width << "x" << height << ", blur sigma " << sigma << ", options " << options
            << ": LPIPS to the photograph " << out->lpips_blurred << " blurred, " << out->lpips_restored
            << " restored; PSNR " << psnr(out->render, out->sharp) << " / " << psnr(out->image, out->sharp)
            << " dB; detail " << detail(out->sharp) << " photograph, " << detail(out->render) << " blurred, "
            << detail(out->image) << " restored\n";
}

// The default 4x shrink on a heavily blurred render (neither side of the crop a multiple of 4, so the resize back
// to the render's exact size is exercised).
TEST(RestoreGeneratorTest, RestoresAHeavilyBlurredFernRenderTowardsThePhotograph) {
  if (auto reason = test::real_weights_skip_reason()) GTEST_SKIP() << *reason;
  FernRestoration r;
  ASSERT_NO_FATAL_FAILURE(restore_fern(100, 120, 190, 254, 2.5, "", &r));
  EXPECT_LT(r.lpips_restored, r.lpips_blurred - 0.03);
  EXPECT_GT(psnr(r.image, r.sharp), psnr(r.render, r.sharp)) << "restored, not replaced: closer to the photograph";
  EXPECT_GT(detail(r.image), detail(r.render) * 1.2);

  FernRestoration again;
  ASSERT_NO_FATAL_FAILURE(restore_fern(100, 120, 190, 254, 2.5, "", &again));
  EXPECT_TRUE(at::equal(again.image, r.image)) << "the same request must give the same image";
}

// Without the shrink (downscale 1) a mildly blurred render is restored too.
TEST(RestoreGeneratorTest, WithoutTheShrinkRestoresAMildlyBlurredFernRender) {
  if (auto reason = test::real_weights_skip_reason()) GTEST_SKIP() << *reason;
  FernRestoration r;
  ASSERT_NO_FATAL_FAILURE(restore_fern(130, 200, 72, 96, 1.5, R"({"downscale": 1})", &r));
  EXPECT_LT(r.lpips_restored, r.lpips_blurred - 0.05);
  EXPECT_GT(detail(r.image), detail(r.render) * 1.2);
}

struct RestoreComposeTest : test::TempDirTest {};

// compose = reproject: a render covering the left half of a plane's view, a reference to the right whose warp
// misses the left border; each region takes what the header's formula says.
TEST_F(RestoreComposeTest, TheWarpIsComposedWhereItCoversAndTheRestorationElsewhere) {
  // Random weights of the x4plus layout (what the backend loads): the composition, not the restoration, is tested.
  test::write_random_rrdbnet(restore::RrdbNetConfig{}, 11, dir_ / "x4plus_random.safetensors");
  RestoreOptions options;
  options.weights = (dir_ / "x4plus_random.safetensors").string();
  options.compose = "reproject";
  absl::StatusOr<std::unique_ptr<RestoreGenerator>> composing = RestoreGenerator::create(options);
  ASSERT_TRUE(composing.ok()) << composing.status();
  options.compose = "none";
  absl::StatusOr<std::unique_ptr<RestoreGenerator>> plain = RestoreGenerator::create(options);
  ASSERT_TRUE(plain.ok()) << plain.status();
  EXPECT_EQ((*composing)->name(), "restore 1 compose:reproject");
  EXPECT_EQ((*plain)->name(), "restore 1");

  const int w = 40, h = 32;
  const Camera pseudo = camera_looking_down_z(w, h, 40, {0, 0, 0});
  const ReferenceView reference = plane_view(camera_looking_down_z(w, h, 40, {0.8, 0, 0}));
  GenerationRequest q = render_request(blurred(plane_view(pseudo).image), pseudo);
  q.render_alpha.slice(1, w / 2).zero_();
  q.references = {reference};
  q.strength = 0.25;
  ASSERT_TRUE((*composing)->adapt({reference}, std::nullopt).ok());
  absl::StatusOr<RestoreResult> result = (*composing)->generate_one(q);
  ASSERT_TRUE(result.ok()) << result.status();
  ASSERT_TRUE(result->reprojected.has_value());
  const ReprojectResult& r = *result->reprojected;
  const at::Tensor both = r.render_covered & r.warp_covered, render_only = r.render_covered & ~r.warp_covered,
                   warp_only = ~r.render_covered & r.warp_covered;
  const int64_t n_both = both.sum().item<int64_t>(), n_render = render_only.sum().item<int64_t>(),
                n_warp = warp_only.sum().item<int64_t>();
  ASSERT_GT(n_both, 0);
  ASSERT_GT(n_warp, 0);
  // The reference sits to the right: the pseudo view's left columns are not in its view.
  ASSERT_GT(n_render, 0);
  const auto max_diff_in = [](const at::Tensor& a, const at::Tensor& b, const at::Tensor& mask) {
    return (a - b).abs().masked_select(mask.unsqueeze(-1).expand_as(a)).max().item<double>();
  };
  const at::Tensor blend = (result->restored * 0.75 + r.warped * 0.25).clamp(0, 1);
  EXPECT_LE(max_diff_in(result->image, blend, both), 1e-6);
  EXPECT_LE(max_diff_in(result->image, result->restored, render_only), 1e-6);
  EXPECT_LE(max_diff_in(result->image, r.image, warp_only), 1e-6);
  EXPECT_GT(max_diff_in(result->restored, r.warped, both), 0.05) << "the regions must be told apart";

  // The restoration is the plain mode's output on the same render, and through generate() the image is the same.
  absl::StatusOr<std::vector<at::Tensor>> plain_out = (*plain)->generate({q});
  ASSERT_TRUE(plain_out.ok()) << plain_out.status();
  EXPECT_TRUE(at::equal(plain_out->front(), result->restored));
  absl::StatusOr<std::vector<at::Tensor>> composed_out = (*composing)->generate({q, q});
  ASSERT_TRUE(composed_out.ok()) << composed_out.status();
  ASSERT_EQ(composed_out->size(), 2u);
  EXPECT_TRUE(at::equal(composed_out->at(1), result->image));

  // Composing needs references, and its request errors name the request among several.
  GenerationRequest lonely = q;
  lonely.references.clear();
  const absl::Status status = (*composing)->generate({q, lonely}).status();
  EXPECT_TRUE(contains(std::string(status.message()), "request 1 has no references")) << status;
  EXPECT_TRUE((*plain)->generate({lonely}).ok()) << "the plain mode does not use references";
}

TEST_F(RestoreComposeTest, RequestErrorsAndNotes) {
  test::write_random_rrdbnet(restore::RrdbNetConfig{}, 2, dir_ / "x4plus_random.safetensors");
  absl::StatusOr<std::unique_ptr<Generator>> generator =
      make_generator("restore", nlohmann::json{{"weights", (dir_ / "x4plus_random.safetensors").string()}}.dump());
  ASSERT_TRUE(generator.ok()) << generator.status();
  EXPECT_EQ((*generator)->weights_identity(), "realesrgan=" + (dir_ / "x4plus_random.safetensors").string());
  const Camera camera = camera_looking_down_z(16, 12, 20, {0, 0, 0});
  const GenerationRequest good = render_request(at::full({12, 16, 3}, 0.5f), camera);
  GenerationRequest wrong_size = good;
  wrong_size.render_rgb = at::zeros({12, 15, 3});
  GenerationRequest not_finite = good;
  not_finite.render_rgb = at::full({12, 16, 3}, NAN);
  for (const auto& [request, words] : std::vector<std::pair<GenerationRequest, std::string>>{
           {wrong_size, "request 1 render_rgb is 12x15x3, expected 12x16x3"},
           {not_finite, "request 1 render_rgb has NaN"},
       }) {
    const absl::Status status = (*generator)->generate({good, request}).status();
    EXPECT_TRUE(absl::IsInvalidArgument(status)) << status;
    EXPECT_TRUE(contains(std::string(status.message()), words)) << status;
  }
  GenerationRequest asking = good;
  asking.ip_adapter_scale = 0.5;
  ASSERT_TRUE((*generator)->generate({good, asking}).ok());
  ASSERT_EQ((*generator)->notes().size(), 1u);
  EXPECT_TRUE(contains((*generator)->notes()[0], "restore has no IP-Adapter: 1/2 requests"))
      << (*generator)->notes()[0];
  ASSERT_TRUE((*generator)->adapt({plane_view(camera)}, SceneAdaptation{4, 50}).ok());
  ASSERT_EQ((*generator)->notes().size(), 1u);
  EXPECT_TRUE(contains((*generator)->notes()[0], "the 50 LoRA steps (rank 4) asked for were not run"));
}

TEST(RestoreOptionsTest, BadOptionsAreRejectedNamingTheKey) {
  const auto message = [](const std::string& json) {
    return std::string(make_generator("restore", json).status().message());
  };
  EXPECT_TRUE(contains(message(R"({"tiles": 64})"), "unknown restore option 'tiles'"));
  EXPECT_TRUE(contains(message(R"({"tiles": 64})"), "did you mean 'tile'"));
  EXPECT_TRUE(contains(message(R"({"compose": "warp"})"), "'compose' = \"warp\": must be none or reproject"));
  EXPECT_TRUE(contains(message(R"({"tile": -1})"), "'tile' = -1: must be an integer >= 0"));
  EXPECT_TRUE(contains(message(R"({"dtype": "bfloat16"})"), "'dtype'"));
  EXPECT_TRUE(contains(message(R"({"dtype": "float16"})"), "restore option 'dtype': float16 needs CUDA"));
  EXPECT_TRUE(contains(message(R"({"device": "tpu"})"), "restore option 'device': 'tpu' is not a device"));
  EXPECT_TRUE(contains(message("[1]"), "restore options must be a JSON object"));
  RestoreOptions options;
  options.tile_pad = -2;
  EXPECT_TRUE(contains(std::string(RestoreGenerator::create(options).status().message()), "'tile_pad' = -2"));
}

TEST(RestoreOptionsTest, MissingWeightsNameTheSetupCommand) {
  absl::Status status = make_generator("restore", R"({"weights": "/nonexistent/x4.safetensors"})").status();
  EXPECT_TRUE(absl::IsNotFound(status)) << status;
  EXPECT_TRUE(contains(std::string(status.message()), "'/nonexistent/x4.safetensors': run `bash scripts/setup.sh`"))
      << status;
  // The default file lives in $GAPS_CACHE.
  const char* saved = std::getenv("GAPS_CACHE");
  const std::string before = saved ? saved : "";
  const std::filesystem::path empty_cache = std::filesystem::path(::testing::TempDir()) / "gaps_restore_empty_cache";
  setenv("GAPS_CACHE", empty_cache.c_str(), 1);
  status = make_generator("restore", "").status();
  if (saved) {
    setenv("GAPS_CACHE", before.c_str(), 1);
  } else {
    unsetenv("GAPS_CACHE");
  }
  EXPECT_TRUE(absl::IsNotFound(status)) << status;
  EXPECT_TRUE(
      contains(std::string(status.message()), (empty_cache / "realesrgan" / "realesrgan-x4plus.safetensors").string()))
      << status;
  EXPECT_TRUE(contains(std::string(status.message()), "bash scripts/setup.sh")) << status;
}

TEST(RestoreOptionsTest, TheRegistryKnowsTheBackendAndItsDevice) {
  const std::vector<std::string> known = known_generator_backends();
  EXPECT_EQ(known, (std::vector<std::string>{"reproject", "restore", "sdxl"}));
  EXPECT_TRUE(generator_backend_uses_device("restore"));
  EXPECT_FALSE(generator_backend_uses_device("reproject"));
  absl::StatusOr<RestoreOptions> options =
      parse_restore_options(R"({"device": "cuda:1", "tile": 64, "tile_pad": 12, "compose": "reproject"})");
  ASSERT_TRUE(options.ok()) << options.status();
  EXPECT_EQ(options->device, "cuda:1");
  EXPECT_EQ(options->tile, 64);
  EXPECT_EQ(options->tile_pad, 12);
  EXPECT_EQ(options->compose, "reproject");
  EXPECT_EQ(options->dtype, "auto");
  EXPECT_EQ(options->weights, "");
}

}  // namespace
}  // namespace gaps

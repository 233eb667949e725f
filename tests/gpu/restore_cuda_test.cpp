// Real-ESRGAN x4plus on CUDA (diffusion_worker/restore/): float16, as the restore backend runs it there by
// default, and float32 against the CPU's float32 on a crop of a fern photograph; the backend on CUDA gives what
// it gives on the CPU.
#include <ATen/ATen.h>
#include <ATen/core/grad_mode.h>
#include <gtest/gtest.h>

#include <iostream>

#include "diffusion_worker/backend_registry.h"
#include "diffusion_worker/restore/realesrgan_weights.h"
#include "diffusion_worker/restore/rrdbnet.h"
#include "tests/gpu/require_cuda.h"
#include "tests/restore_test_util.h"

namespace gaps {
namespace {

using restore::RrdbNet;

struct Difference {
  double max = 0, mean = 0;
};

Difference difference(const at::Tensor& a, const at::Tensor& b) {
  const at::Tensor d = (a.to(at::kCPU, at::kFloat) - b.to(at::kCPU, at::kFloat)).abs();
  return {d.max().item<double>(), d.mean().item<double>()};
}

TEST(RealEsrganCuda, Float16AndFloat32OnCudaMatchTheCpu) {
  GAPS_REQUIRE_CUDA();
  if (auto reason = test::real_weights_skip_reason()) GTEST_SKIP() << *reason;
  const auto path = restore::default_realesrgan_weights_path();
  absl::StatusOr<RrdbNet> cpu = restore::load_rrdbnet(path, {}, at::kFloat, at::kCPU);
  absl::StatusOr<RrdbNet> cuda32 = restore::load_rrdbnet(path, {}, at::kFloat, at::kCUDA);
  absl::StatusOr<RrdbNet> cuda16 = restore::load_rrdbnet(path, {}, at::kHalf, at::kCUDA);
  ASSERT_TRUE(cpu.ok() && cuda32.ok() && cuda16.ok()) << cpu.status() << cuda32.status() << cuda16.status();
  const at::Tensor x = test::fern_crop(150, 200, 48, 64).permute({2, 0, 1}).unsqueeze(0).contiguous();
  at::NoGradGuard no_grad;
  // cuDNN may convolve float32 in TF32, which is not what the float32 comparison is about.
  at::Context& context = at::globalContext();
  const bool tf32 = context.allowTF32CuDNN();
  context.setAllowTF32CuDNN(false);
  const at::Tensor expected = (*cpu)(x);
  const Difference d32 = difference((*cuda32)(x.cuda()), expected);
  const Difference d16 = difference((*cuda16)(x.to(at::kCUDA, at::kHalf)), expected);
  context.setAllowTF32CuDNN(tf32);
  std::cout << "x4plus on fern 64x48 vs CPU float32: CUDA float32 max " << d32.max << " mean " << d32.mean
            << "; CUDA float16 max " << d16.max << " mean " << d16.mean << "\n";
  EXPECT_LE(d32.max, 1e-3);
  // PyTorch's float16 on the CPU lands at max 0.006, mean 3e-4 from float32 on this crop.
  EXPECT_LE(d16.max, 0.02);
  EXPECT_LE(d16.mean, 1e-3);
}

TEST(RealEsrganCuda, TheBackendOnCudaGivesTheCpusImage) {
  GAPS_REQUIRE_CUDA();
  if (auto reason = test::real_weights_skip_reason()) GTEST_SKIP() << *reason;
  const at::Tensor render = test::fern_crop(0, 0, 378, 504);
  GenerationRequest q;
  q.camera.width = 504;
  q.camera.height = 378;
  q.camera.fx = q.camera.fy = 400;
  q.render_rgb = render;
  std::vector<at::Tensor> images;
  // Tiles change the image (the network sees less context at their borders), so tiled CUDA is held to tiled CPU.
  for (const char* options : {R"({"device": "cpu"})", R"({"device": "cuda"})", R"({"device": "cpu", "tile": 32})",
                              R"({"device": "cuda", "tile": 32})"}) {
    absl::StatusOr<std::unique_ptr<Generator>> generator = make_generator("restore", options);
    ASSERT_TRUE(generator.ok()) << generator.status();
    absl::StatusOr<std::vector<at::Tensor>> out = (*generator)->generate({q});
    ASSERT_TRUE(out.ok()) << out.status();
    ASSERT_EQ(out->front().sizes(), render.sizes());
    EXPECT_TRUE(out->front().device().is_cpu());
    images.push_back(out->front());
  }
  const Difference whole = difference(images[1], images[0]), tiled = difference(images[3], images[2]);
  std::cout << "restore backend on fern 504x378, CUDA (float16) vs CPU: max " << whole.max << " mean " << whole.mean
            << "; in tiles of 32, CUDA vs CPU: max " << tiled.max << " mean " << tiled.mean << "\n";
  EXPECT_LE(whole.mean, 1e-3);
  EXPECT_LE(tiled.mean, 1e-3);
}

}  // namespace
}  // namespace gaps

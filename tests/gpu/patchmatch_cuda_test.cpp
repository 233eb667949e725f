// PatchMatch stereo's CUDA kernels: the synthetic scenes' accuracy bars of patchmatch_test.cpp on the GPU, and
// agreement with the CPU path.
#include <algorithm>
#include <iostream>
#include <string>
#include <vector>

#include <ATen/ATen.h>
#include <gtest/gtest.h>

#include "gs_trainer/init/patchmatch.h"
#include "tests/gpu/require_cuda.h"
#include "tests/synthetic_stereo.h"

namespace gaps {
namespace {

namespace ss = synthetic_stereo;

struct SceneCase {
  const char* name;
  ss::Scene scene;
  double min_valid;  // as in patchmatch_test.cpp
};

std::vector<SceneCase> scenes() {
  return {{"plane", ss::slanted_plane(), 0.75}, {"sphere", ss::sphere_before_plane(), 0.5}};
}

PatchMatchInput on_device(PatchMatchInput in, const at::Device& device) {
  for (at::Tensor& image : in.images) image = image.to(device);
  return in;
}

TEST(PatchMatchCuda, RecoversTheSyntheticScenes) {
  GAPS_REQUIRE_CUDA_KERNELS();
  for (const SceneCase& c : scenes()) {
    const std::vector<ss::View> views = ss::render_views(c.scene);
    const auto result =
        patchmatch_stereo(on_device(ss::stereo_input(views, ss::kDepthRange), at::kCUDA), ss::small_view_options());
    ASSERT_TRUE(result.ok()) << result.status();
    ASSERT_TRUE((*result)[0].depth.device().is_cpu());
    const ss::Accuracy a = ss::measure_all(c.scene, views, *result);
    EXPECT_GE(a.accurate_fraction(), 0.9) << c.name << ": " << a.accurate << " of " << a.valid << " within 1%";
    EXPECT_GE(a.valid_fraction(), c.min_valid) << c.name << ": " << a.valid << " of " << a.covisible;
  }
}

// Both paths run patchmatch_math.h's float code with correctly rounded operations only, no FMA contraction
// (init/CMakeLists.txt), the same counter-based random numbers and the same grey input (prepared on the CPU),
// so they should keep the same hypothesis at every pixel and return equal maps. The bar allows 1% of pixels
// to differ (validity, or depth by more than 0.1%) so that one operation a compiler rounds differently does
// not fail it: such a difference flips a near-tie, which propagation then spreads over a few neighbours; a
// semantic difference between the paths (another candidate order, another random draw) changes most pixels.
TEST(PatchMatchCuda, AgreesWithTheCpu) {
  GAPS_REQUIRE_CUDA_KERNELS();
  for (const SceneCase& c : scenes()) {
    const std::vector<ss::View> views = ss::render_views(c.scene);
    const PatchMatchInput in = ss::stereo_input(views, ss::kDepthRange);
    const auto cpu = patchmatch_stereo(in, ss::small_view_options());
    const auto gpu = patchmatch_stereo(on_device(in, at::kCUDA), ss::small_view_options());
    ASSERT_TRUE(cpu.ok() && gpu.ok());
    int64_t pixels = 0, agree = 0, equal = 0;
    for (size_t v = 0; v < views.size(); ++v) {
      const at::Tensor a = (*cpu)[v].depth, b = (*gpu)[v].depth;
      const at::Tensor same_validity = (a > 0) == (b > 0);
      const at::Tensor close = ((a - b).abs() <= 1e-3 * a) | ((a == 0) & (b == 0));
      pixels += a.numel();
      agree += (same_validity & close).sum().item<int64_t>();
      equal += a.eq(b).logical_and((*cpu)[v].normal.eq((*gpu)[v].normal).all(2)).sum().item<int64_t>();
    }
    std::cout << c.name << ": " << equal << " of " << pixels << " pixels bitwise equal, " << agree << " agree\n";
    EXPECT_GE(static_cast<double>(agree) / pixels, 0.99) << c.name;
  }
}

// A build without the kernels says so instead of computing anything.
TEST(PatchMatchCuda, ABuildWithoutTheKernelsNamesThem) {
#if defined(GAPS_CUDA_KERNELS)
  GTEST_SKIP() << "built with the CUDA kernels";
#else
  GAPS_REQUIRE_CUDA();
  const std::vector<ss::View> views = ss::render_views(ss::slanted_plane(), 24, 18);
  const auto result = patchmatch_stereo(on_device(ss::stereo_input(views, ss::kDepthRange), at::kCUDA));
  ASSERT_FALSE(result.ok());
  EXPECT_EQ(result.status().code(), absl::StatusCode::kFailedPrecondition);
  EXPECT_NE(result.status().message().find("built without CUDA kernels"), std::string::npos) << result.status();
#endif
}

}  // namespace
}  // namespace gaps

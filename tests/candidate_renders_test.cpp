// Scoring a candidate pool in batches (gaps/candidate_renders.h): the batched statistics are those of one
// render and one measurement per view, whatever the batch boundaries and image sizes.
#include <vector>

#include <ATen/ATen.h>
#include <gtest/gtest.h>
#include <Eigen/Geometry>

#include "gs_trainer/gaps/candidate_renders.h"
#include "gs_trainer/gaps/scores.h"
#include "gs_trainer/model/render.h"
#include "tests/raster_test_util.h"

namespace gaps {
namespace {

Camera camera_at(int w, int h, double yaw, double shift) {
  Camera c;
  c.width = w;
  c.height = h;
  c.fx = c.fy = 0.9 * w;
  c.cx = 0.5 * w;
  c.cy = 0.5 * h;
  c.R = Eigen::AngleAxisd(yaw, Eigen::Vector3d::UnitY()).toRotationMatrix();
  c.t = Eigen::Vector3d(shift, -0.05, 0.2);
  return c;
}

TEST(RenderStatistics, RowsEqualMeasuringEachRender) {
  at::manual_seed(3);
  const at::Tensor images = at::rand({3, 9, 11, 3}, at::kFloat);
  const at::Tensor alphas = at::rand({3, 9, 11}, at::kFloat);
  const GapsConfig c;
  const at::Tensor rows = render_statistics(images, alphas, c);
  ASSERT_EQ(rows.sizes(), at::IntArrayRef({3, 4}));
  for (int64_t k = 0; k < 3; ++k) {
    const CandidateMeasurements m = measure_render(images[k], alphas[k], 0, 0, std::nullopt, c);
    EXPECT_NEAR(rows[k][0].item<double>(), m.mean_alpha, 1e-12);
    EXPECT_NEAR(rows[k][1].item<double>(), m.entropy_mean, 1e-12);
    EXPECT_NEAR(rows[k][2].item<double>(), m.coverage, 1e-12);
    EXPECT_NEAR(rows[k][3].item<double>(), m.contrast, 1e-12);
    EXPECT_NEAR(m.mean_alpha, alphas[k].to(at::kDouble).mean().item<double>(), 1e-12);
    EXPECT_NEAR(m.entropy_mean, local_entropy_map(images[k], c.entropy_bins).mean().item<double>(), 1e-6);
  }
  EXPECT_THROW(render_statistics(images, alphas.narrow(1, 0, 4), c), c10::Error);
}

// 70 views in runs of two sizes: batches of 32 (the most a GPU takes) and of 7, cut where the size changes, and
// the CPU's automatic one view at a time.
TEST(CandidateStatistics, EqualOneRenderAndMeasurementPerView) {
  const GaussianModel m = test::random_model(60, 4, at::kFloat, 1);
  const GapsConfig c;
  std::vector<Camera> cameras;
  for (int k = 0; k < 70; ++k) {
    const bool small = (k / 5) % 3 == 1;
    cameras.push_back(camera_at(small ? 23 : 32, small ? 17 : 24, 0.01 * k - 0.3, 0.004 * k));
  }
  const at::Tensor rows = candidate_statistics(m, cameras, c, 32);
  ASSERT_EQ(rows.sizes(), at::IntArrayRef({70, 4}));
  EXPECT_TRUE(at::equal(candidate_statistics(m, cameras, c, 7), rows));
  EXPECT_TRUE(at::equal(candidate_statistics(m, cameras, c), rows));
  for (size_t k = 0; k < cameras.size(); ++k) {
    const RenderOutput r = render(m, cameras[k]);
    const CandidateMeasurements one = measure_render(r.rgb.clamp(0, 1), r.alpha, 0, 0, std::nullopt, c);
    const int64_t i = static_cast<int64_t>(k);
    EXPECT_NEAR(rows[i][0].item<double>(), one.mean_alpha, 1e-12) << "view " << k;
    EXPECT_NEAR(rows[i][1].item<double>(), one.entropy_mean, 1e-12) << "view " << k;
    EXPECT_NEAR(rows[i][2].item<double>(), one.coverage, 1e-12) << "view " << k;
    EXPECT_NEAR(rows[i][3].item<double>(), one.contrast, 1e-12) << "view " << k;
  }
  EXPECT_GT(rows.select(1, 0).min().item<double>(), 0.01) << "every view should see some of the Gaussians";
  EXPECT_EQ(candidate_statistics(m, {}, c).size(0), 0);
}

TEST(CandidateStatistics, BatchShrinksWithTheWorkingMemoryOfAView) {
  const GapsConfig c;
  const at::Device gpu(at::kCUDA, 0);
  EXPECT_EQ(candidate_batch_size(10, 64, 48, gpu, c), 32) << "a tiny model's views should fill the largest batch";
  EXPECT_EQ(candidate_batch_size(10, 20000, 20000, gpu, c), 1);
  EXPECT_EQ(candidate_batch_size(100'000'000, 64, 48, gpu, c), 1);
  const int lo = candidate_batch_size(300'000, 1000, 1000, gpu, c),
            hi = candidate_batch_size(300'000, 500, 500, gpu, c);
  EXPECT_GE(lo, 1);
  EXPECT_LT(lo, hi);
  EXPECT_LE(hi, 32);
  EXPECT_GT(candidate_batch_size(300'000, 500, 500, gpu, c), candidate_batch_size(1'000'000, 500, 500, gpu, c));
  EXPECT_EQ(candidate_batch_size(10, 64, 48, at::Device(at::kCPU), c), 1) << "the CPU renders one view at a time";
}

}  // namespace
}  // namespace gaps

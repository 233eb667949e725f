// The paper's two-stage generation (eq. two_stage, diffusion_worker/sdxl/two_stage.h): the uncovered mask
// (depth < tau_d), its fraction, the 15 x 15 dilation, the 2% threshold and the composite, against
// hand-computed values; the inpainting itself runs on the tiny SD2 inpainting fixture, and through the
// `sdxl` backend's options (inpaint, inpaint_depth_threshold) on the tiny SDXL and SD2 models.
#include <limits>

#include <ATen/ATen.h>
#include <ATen/CPUGeneratorImpl.h>
#include <gtest/gtest.h>

#include "diffusion_worker/backend_registry.h"
#include "diffusion_worker/sdxl/inpaint_pipeline.h"
#include "diffusion_worker/sdxl/two_stage.h"
#include "tests/sdxl_test_util.h"

namespace gaps::sdxl {
namespace {

std::string inpaint_model_dir() { return std::string(GAPS_TEST_SCRIPTS_DIR) + "/fixtures/sd2_inpaint_tiny/model"; }

TEST(TwoStageTest, UncoveredWhereDepthIsBelowTheThreshold) {
  const at::Tensor depth = at::tensor({0.0f, 0.5f, 2.0f, 1.0f, 0.99f, 3.0f}).view({1, 2, 3});
  const at::Tensor expected = at::tensor({1.0f, 1.0f, 0.0f, 0.0f, 1.0f, 0.0f}).view({1, 1, 2, 3});
  EXPECT_TRUE(at::equal(uncovered_mask(depth, 1.0), expected));
  EXPECT_TRUE(at::equal(uncovered_mask(depth.unsqueeze(1), 1.0), expected));  // B x 1 x H x W as well
  EXPECT_EQ(uncovered_fractions(expected), (std::vector<double>{0.5}));
}

TEST(TwoStageTest, DilatesWithASquareKernelClippedAtTheBorder) {
  at::Tensor mask = at::zeros({1, 1, 20, 20});
  mask[0][0][2][17] = 1;
  at::Tensor expected = at::zeros({1, 1, 20, 20});
  expected.slice(2, 0, 10).slice(3, 10, 20).fill_(1);  // rows 2 - 7 .. 2 + 7, columns 17 - 7 .. 17 + 7, clipped
  EXPECT_TRUE(at::equal(dilate_mask(mask, 15), expected));
  at::Tensor small = at::zeros({1, 1, 5, 5});
  small[0][0][2][2] = 1;
  at::Tensor block = at::zeros({1, 1, 5, 5});
  block.slice(2, 1, 4).slice(3, 1, 4).fill_(1);
  EXPECT_TRUE(at::equal(dilate_mask(small, 3), block));
  EXPECT_TRUE(at::equal(dilate_mask(small, 1), small));
  EXPECT_THROW(dilate_mask(small, 4), c10::Error);
}

TEST(TwoStageTest, CompositesPerEquationTwoStage) {
  const at::Tensor stage1 = at::full({1, 3, 1, 3}, 0.2f), stage2 = at::full({1, 3, 1, 3}, 0.9f);
  const at::Tensor mask = at::tensor({1.0f, 0.0f, 0.25f}).view({1, 1, 1, 3});
  const at::Tensor out = composite_two_stage(stage1, stage2, mask);
  const at::Tensor expected =
      at::tensor({0.9f, 0.2f, 0.25f * 0.9f + 0.75f * 0.2f}).view({1, 1, 1, 3}).expand({1, 3, 1, 3});
  EXPECT_TRUE(at::allclose(out, expected, 0, 1e-7));
}

class TwoStageGenerateTest : public ::testing::Test {
 protected:
  void SetUp() override {
    auto pipeline = InpaintPipeline::load(inpaint_model_dir(), InpaintPipelineOptions{});
    ASSERT_TRUE(pipeline.ok()) << pipeline.status();
    pipeline_ = *std::move(pipeline);
    options_.depth_threshold = 0.5;
    options_.inpaint.steps = 2;
    options_.inpaint.guidance_scale = 5.0;
  }
  InpaintPipelineSource source() {
    return [this]() -> absl::StatusOr<InpaintPipeline*> {
      ++calls_;
      return pipeline_.get();
    };
  }
  std::unique_ptr<InpaintPipeline> pipeline_;
  TwoStageOptions options_;
  int calls_ = 0;
};

// 50 x 50 views: 2% is 50 pixels. View 0 has exactly 50 uncovered (kept), view 1 has 51 (inpainted).
TEST_F(TwoStageGenerateTest, InpaintsOnlyViewsAboveTwoPercentAndKeepsCoveredPixels) {
  at::Generator g = at::make_generator<at::CPUGeneratorImpl>(5);
  const at::Tensor stage1 = at::rand({2, 3, 50, 50}, g);
  at::Tensor depth = at::full({2, 50, 50}, 2.0f);
  depth[0].slice(0, 5, 10).slice(1, 0, 10).fill_(0);    // 5 x 10 = 50 pixels
  depth[1].slice(0, 10, 17).slice(1, 20, 27).fill_(0);  // 7 x 7 = 49 pixels
  depth[1][30][40] = 0.49f;
  depth[1][45][3] = 0.1f;
  auto result = two_stage_generate(stage1, depth, {"a fern"}, {3, 4}, options_, source());
  ASSERT_TRUE(result.ok()) << result.status();
  EXPECT_EQ(calls_, 1);
  EXPECT_EQ(result->uncovered, (std::vector<double>{50.0 / 2500, 51.0 / 2500}));
  EXPECT_EQ(result->inpainted, (std::vector<bool>{false, true}));
  EXPECT_TRUE(at::equal(result->images[0], stage1[0]));
  // View 1: the inpainting of its dilated mask inside, the stage-1 image outside.
  const at::Tensor mask = dilate_mask(uncovered_mask(depth.slice(0, 1, 2), 0.5), 15);
  // The 7 x 7 block grown to 21 x 21 (rows 3-23, columns 13-33); (30, 40) to 15 x 15 (rows 23-37, columns
  // 33-47), sharing pixel (23, 33) with it; (45, 3) to rows 38-49 x columns 0-10 at the border.
  EXPECT_EQ(mask.sum().item<double>(), 21 * 21 + 15 * 15 - 1 + 12 * 11);
  auto stage2 = pipeline_->inpaint(stage1.slice(0, 1, 2), mask, {"a fern"}, options_.inpaint, {4});
  ASSERT_TRUE(stage2.ok()) << stage2.status();
  const at::Tensor inside = mask[0][0] > 0.5;
  const at::Tensor out = result->images[1];
  EXPECT_TRUE(
      at::equal(out.masked_select(inside.expand({3, 50, 50})), (*stage2)[0].masked_select(inside.expand({3, 50, 50}))));
  EXPECT_TRUE(
      at::equal(out.masked_select(~inside.expand({3, 50, 50})), stage1[1].masked_select(~inside.expand({3, 50, 50}))));
  EXPECT_GT((out - stage1[1]).abs().max().item<double>(), 1e-3);  // the inpainting changed something
}

TEST_F(TwoStageGenerateTest, SkipsTheInpaintingModelWhenNoViewNeedsIt) {
  const at::Tensor stage1 = at::rand({1, 3, 50, 50});
  const auto failing = []() -> absl::StatusOr<InpaintPipeline*> { return absl::InternalError("must not load"); };
  auto result = two_stage_generate(stage1, at::ones({1, 1, 50, 50}), {"x"}, {1}, options_, failing);
  ASSERT_TRUE(result.ok()) << result.status();
  EXPECT_TRUE(at::equal(result->images, stage1));
  // A view that needs it surfaces the loading error.
  auto needs = two_stage_generate(stage1, at::zeros({1, 1, 50, 50}), {"x"}, {1}, options_, failing);
  ASSERT_FALSE(needs.ok());
  EXPECT_EQ(needs.status().message(), "must not load");
}

TEST_F(TwoStageGenerateTest, RejectsBadInputs) {
  const at::Tensor stage1 = at::rand({1, 3, 8, 8});
  const auto message = [&](const at::Tensor& s, const at::Tensor& d, const std::vector<uint64_t>& seeds,
                           const TwoStageOptions& o) {
    auto r = two_stage_generate(s, d, {"x"}, seeds, o, source());
    EXPECT_FALSE(r.ok());
    return r.ok() ? std::string() : std::string(r.status().message());
  };
  EXPECT_TRUE(test::contains_all(message(stage1, at::zeros({1, 8, 7}), {1}, options_), {"depth"}));
  EXPECT_TRUE(test::contains_all(message(at::rand({1, 8, 8}), at::zeros({1, 8, 8}), {1}, options_), {"stage-1"}));
  EXPECT_TRUE(test::contains_all(message(stage1, at::zeros({1, 8, 8}), {1, 2}, options_), {"seed"}));
  TwoStageOptions o = options_;
  o.depth_threshold = std::numeric_limits<double>::quiet_NaN();
  EXPECT_TRUE(test::contains_all(message(stage1, at::zeros({1, 8, 8}), {1}, o), {"depth_threshold"}));
  o = options_;
  o.dilation_kernel = 14;
  EXPECT_TRUE(test::contains_all(message(stage1, at::zeros({1, 8, 8}), {1}, o), {"dilation_kernel"}));
  EXPECT_EQ(calls_, 0);
}

// The `sdxl` backend with two-stage inpainting.
std::string backend_options(const std::string& inpaint_extra) {
  return "{\"weights\": \"" + test::sdxl_model_dir() + "\", \"steps\": 4, \"prompt\": \"a fern\"" + inpaint_extra + "}";
}

GenerationRequest request_with_depth(const at::Tensor& depth, uint64_t seed) {
  GenerationRequest r;
  at::Generator g = at::make_generator<at::CPUGeneratorImpl>(seed);
  r.render_rgb = at::rand({depth.size(0), depth.size(1), 3}, g);
  r.render_depth = depth;
  r.render_alpha = at::ones_like(depth);
  r.strength = 0.5;
  r.seed = seed;
  return r;
}

// tau_d comes with the request (the trainer's GapsConfig) or from the option; a request with neither is an error.
TEST(TwoStageBackendTest, DepthThresholdFromTheRequestOrTheOption) {
  auto without = make_generator("sdxl", backend_options(", \"inpaint\": \"/nonexistent/sd2-inpainting\""));
  ASSERT_TRUE(without.ok()) << without.status();
  GenerationRequest covered = request_with_depth(at::ones({12, 8}), 3);
  const absl::Status missing = (*without)->generate({covered}).status();
  EXPECT_TRUE(test::contains_all(std::string(missing.message()), {"request 0", "inpaint_depth_threshold"}));
  covered.inpaint = InpaintSettings{};
  EXPECT_TRUE((*without)->generate({covered}).ok());
  auto bad = make_generator("sdxl", backend_options(", \"inpaint_steps\": 0"));
  ASSERT_FALSE(bad.ok());
  EXPECT_TRUE(test::contains_all(std::string(bad.status().message()), {"inpaint_steps"}));
  auto even = make_generator("sdxl", backend_options(", \"inpaint_dilation\": 14"));
  ASSERT_FALSE(even.ok());
  EXPECT_TRUE(test::contains_all(std::string(even.status().message()), {"inpaint_dilation", "odd"}));
  auto fraction = make_generator("sdxl", backend_options(", \"inpaint_uncovered_fraction\": 1.5"));
  ASSERT_FALSE(fraction.ok());
  EXPECT_TRUE(test::contains_all(std::string(fraction.status().message()), {"inpaint_uncovered_fraction"}));
  auto unknown = make_generator("sdxl", backend_options(", \"inpaint_kernel\": 3"));
  ASSERT_FALSE(unknown.ok());
  EXPECT_TRUE(test::contains_all(std::string(unknown.status().message()), {"unknown", "inpaint_depth_threshold"}));
}

TEST(TwoStageBackendTest, InpaintsTheUncoveredPixelsOfTheImg2ImgResult) {
  auto plain = make_generator("sdxl", backend_options(""));
  ASSERT_TRUE(plain.ok()) << plain.status();
  auto two_stage =
      make_generator("sdxl", backend_options(", \"inpaint\": \"" + inpaint_model_dir() +
                                             "\", \"inpaint_depth_threshold\": 0.5, \"inpaint_steps\": 2, "
                                             "\"inpaint_dilation\": 15, \"inpaint_uncovered_fraction\": 0.02"));
  ASSERT_TRUE(two_stage.ok()) << two_stage.status();
  // 23 x 20 (padded to 24 x 20 for both models), 16 of 460 pixels uncovered.
  at::Tensor depth = at::ones({23, 20});
  depth.slice(0, 2, 6).slice(1, 2, 6).fill_(0);
  const GenerationRequest r = request_with_depth(depth, 11);
  auto stage1 = (*plain)->generate({r});
  auto out = (*two_stage)->generate({r});
  ASSERT_TRUE(stage1.ok()) << stage1.status();
  ASSERT_TRUE(out.ok()) << out.status();
  ASSERT_EQ((*out)[0].sizes(), r.render_rgb.sizes());
  // The same as two_stage_generate on the stage-1 image with the same prompt and seed.
  auto pipeline = InpaintPipeline::load(inpaint_model_dir(), InpaintPipelineOptions{});
  ASSERT_TRUE(pipeline.ok()) << pipeline.status();
  TwoStageOptions options;
  options.depth_threshold = 0.5;
  options.inpaint.steps = 2;
  auto direct = two_stage_generate((*stage1)[0].permute({2, 0, 1}).unsqueeze(0), depth.unsqueeze(0), {"a fern"}, {11},
                                   options, [&]() -> absl::StatusOr<InpaintPipeline*> { return pipeline->get(); });
  ASSERT_TRUE(direct.ok()) << direct.status();
  ASSERT_EQ(direct->inpainted, (std::vector<bool>{true}));
  test::expect_close((*out)[0], direct->images[0].permute({1, 2, 0}), 1e-5, "backend vs two_stage_generate");
  // Inside the dilated mask (rows and columns 0-12) the inpainting changed the image; outside it is kept.
  const at::Tensor inside = (*out)[0].slice(0, 0, 13).slice(1, 0, 13),
                   before = (*stage1)[0].slice(0, 0, 13).slice(1, 0, 13);
  EXPECT_GT((inside - before).abs().max().item<double>(), 1e-3);
  EXPECT_TRUE(at::equal((*out)[0].slice(0, 13), (*stage1)[0].slice(0, 13)));
  EXPECT_TRUE(at::equal((*out)[0].slice(1, 13), (*stage1)[0].slice(1, 13)));
}

// A request's InpaintSettings replace the options: here 16 of 460 pixels (3.5%) are uncovered at tau_d 0.5.
TEST(TwoStageBackendTest, TheRequestsSettingsReachTheTwoStagePass) {
  auto plain = make_generator("sdxl", backend_options(""));
  auto two_stage =
      make_generator("sdxl", backend_options(", \"inpaint\": \"" + inpaint_model_dir() +
                                             "\", \"inpaint_depth_threshold\": 0.5, \"inpaint_steps\": 2"));
  ASSERT_TRUE(plain.ok()) << plain.status();
  ASSERT_TRUE(two_stage.ok()) << two_stage.status();
  at::Tensor depth = at::ones({23, 20});
  depth.slice(0, 2, 6).slice(1, 2, 6).fill_(0);
  GenerationRequest r = request_with_depth(depth, 11);
  auto stage1 = (*plain)->generate({r});
  ASSERT_TRUE(stage1.ok()) << stage1.status();
  const auto generate_with = [&](const InpaintSettings& settings) {
    GenerationRequest q = r;
    q.inpaint = settings;
    auto out = (*two_stage)->generate({q});
    EXPECT_TRUE(out.ok()) << out.status();
    return out.ok() ? (*out)[0] : at::Tensor();
  };
  EXPECT_TRUE(at::equal(generate_with({0.5, 0.05, 15}), (*stage1)[0])) << "3.5% uncovered is below 5%";
  EXPECT_TRUE(at::equal(generate_with({0.0, 0.02, 15}), (*stage1)[0])) << "no depth is below tau_d 0";
  // Dilation 3: the mask is rows and columns 1-6; the result is two_stage_generate's with that kernel.
  const at::Tensor small = generate_with({0.5, 0.02, 3});
  auto pipeline = InpaintPipeline::load(inpaint_model_dir(), InpaintPipelineOptions{});
  ASSERT_TRUE(pipeline.ok()) << pipeline.status();
  TwoStageOptions options;
  options.depth_threshold = 0.5;
  options.dilation_kernel = 3;
  options.inpaint.steps = 2;
  auto direct = two_stage_generate((*stage1)[0].permute({2, 0, 1}).unsqueeze(0), depth.unsqueeze(0), {"a fern"}, {11},
                                   options, [&]() -> absl::StatusOr<InpaintPipeline*> { return pipeline->get(); });
  ASSERT_TRUE(direct.ok()) << direct.status();
  test::expect_close(small, direct->images[0].permute({1, 2, 0}), 1e-5, "backend with the request's dilation");
  EXPECT_TRUE(at::equal(small.slice(0, 7), (*stage1)[0].slice(0, 7)));
  EXPECT_GT(
      (small.slice(0, 1, 7).slice(1, 1, 7) - (*stage1)[0].slice(0, 1, 7).slice(1, 1, 7)).abs().max().item<double>(),
      1e-3);
}

TEST(TwoStageBackendTest, LoadsTheInpaintingModelOnlyWhenAViewNeedsIt) {
  auto generator = make_generator("sdxl", backend_options(", \"inpaint\": \"/nonexistent/sd2-inpainting\", "
                                                          "\"inpaint_depth_threshold\": 0.5"));
  ASSERT_TRUE(generator.ok()) << generator.status();
  auto plain = make_generator("sdxl", backend_options(""));
  ASSERT_TRUE(plain.ok()) << plain.status();
  const GenerationRequest covered = request_with_depth(at::ones({12, 8}), 3);
  auto kept = (*generator)->generate({covered});
  ASSERT_TRUE(kept.ok()) << kept.status();
  auto reference = (*plain)->generate({covered});
  ASSERT_TRUE(reference.ok());
  EXPECT_TRUE(at::equal((*kept)[0], (*reference)[0]));
  auto uncovered = (*generator)->generate({request_with_depth(at::zeros({12, 8}), 3)});
  ASSERT_FALSE(uncovered.ok());
  EXPECT_TRUE(
      test::contains_all(std::string(uncovered.status().message()), {"/nonexistent/sd2-inpainting", "inpainting"}));
  GenerationRequest no_depth = covered;
  no_depth.render_depth = at::Tensor();
  auto refused = (*generator)->generate({no_depth});
  ASSERT_FALSE(refused.ok());
  EXPECT_TRUE(test::contains_all(std::string(refused.status().message()), {"render_depth"}));
}

}  // namespace
}  // namespace gaps::sdxl

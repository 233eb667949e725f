// SDXL img2img against diffusers' StableDiffusionXLImg2ImgPipeline on the tiny fixture: two images, two
// prompts, strength 0.5 of 4 Euler steps (2 run; and of 6 DDIM / DPM-Solver++ steps), guidance 5, one CPU
// generator seeded 1234 (the same random draws in LibTorch and PyTorch). Tolerance: max abs diff <= 1e-4
// on images in [0, 1]. float16 and bfloat16 on CUDA, and CUDA-graph replay: gpu/sdxl_cuda_test.cpp.
#include <fstream>

#include <ATen/ATen.h>
#include <gtest/gtest.h>
#include <nlohmann/json.hpp>
#include "absl/strings/str_cat.h"

#include "diffusion_worker/sdxl/model_folder.h"
#include "diffusion_worker/sdxl/pipeline.h"
#include "diffusion_worker/sdxl/random_model.h"
#include "tests/sdxl_test_util.h"
#include "tests/test_util.h"

namespace gaps::sdxl {
namespace {

TEST(SdxlPipelineTest, Img2ImgMatchesDiffusers) {
  std::ifstream in(test::sdxl_fixture_dir() + "/reference/img2img.json");
  const nlohmann::json setup = nlohmann::json::parse(in);
  auto pipeline = SdxlPipeline::load(test::sdxl_model_dir(), PipelineOptions{});
  ASSERT_TRUE(pipeline.ok()) << pipeline.status();
  const TensorMap ref = test::sdxl_reference("img2img");
  Img2ImgParams params;
  params.strength = setup["strength"].get<double>();
  params.steps = setup["num_inference_steps"].get<int64_t>();
  params.guidance_scale = setup["guidance_scale"].get<double>();
  auto out = (*pipeline)->img2img(ref.at("image"), setup["prompts"].get<std::vector<std::string>>(), params,
                                  {setup["seed"].get<uint64_t>()});
  ASSERT_TRUE(out.ok()) << out.status();
  test::expect_close(*out, ref.at("out"), 1e-4, "img2img output");
  // A different seed gives a different image (the draws are used).
  auto other = (*pipeline)->img2img(ref.at("image"), setup["prompts"].get<std::vector<std::string>>(), params, {7});
  ASSERT_TRUE(other.ok());
  EXPECT_GT((*other - *out).abs().max().item<double>(), 1e-3);
}

// The other schedulers, built from the folder's Euler config as diffusers' from_config does: 3 of 6
// steps (DPM-Solver++ takes second-order steps).
TEST(SdxlPipelineTest, Img2ImgWithDdimAndDpmSolverMatchesDiffusers) {
  for (const char* kind : {"ddim", "dpmpp2m"}) {
    PipelineOptions options;
    options.scheduler = kind;
    auto pipeline = SdxlPipeline::load(test::sdxl_model_dir(), options);
    ASSERT_TRUE(pipeline.ok()) << pipeline.status();
    const TensorMap ref = test::sdxl_reference(std::string("img2img_") + kind);
    Img2ImgParams params;
    params.strength = 0.5;
    params.steps = 6;
    params.guidance_scale = 5.0;
    auto out =
        (*pipeline)->img2img(ref.at("image"), {"a photo of a fern in a garden", "a bonsai tree"}, params, {1234});
    ASSERT_TRUE(out.ok()) << out.status();
    test::expect_close(*out, ref.at("out"), 1e-4, std::string("img2img with ") + kind);
  }
}

// One batch of images with different strengths (4, 6 and 8 of 8 steps) gives each image what it gives alone: a
// later image joins the batch at its start step, and each start keeps its own scheduler history (DPM-Solver++ is
// multistep; the fixture's scheduler config does not allow PNDM).
TEST(SdxlPipelineTest, Img2ImgWithMixedStrengthsGivesEachImageWhatItGivesAlone) {
  const at::Tensor images = test::sdxl_reference("img2img").at("image");
  const at::Tensor batch = at::cat({images, images.slice(0, 0, 1).flip(3)});
  const std::vector<double> strengths = {1.0, 0.5, 0.75};
  const std::vector<std::string> prompts = {"a fern", "a bonsai tree", "a garden"};
  const std::vector<uint64_t> seeds = {11, 12, 13};
  for (const char* kind : {"euler", "ddim", "dpmpp2m"}) {
    PipelineOptions options;
    options.scheduler = kind;
    auto pipeline = SdxlPipeline::load(test::sdxl_model_dir(), options);
    ASSERT_TRUE(pipeline.ok()) << pipeline.status();
    Img2ImgParams params;
    params.steps = 8;
    params.guidance_scale = 5.0;
    params.strengths = strengths;
    auto mixed = (*pipeline)->img2img(batch, prompts, params, seeds);
    ASSERT_TRUE(mixed.ok()) << mixed.status();
    for (int64_t b = 0; b < batch.size(0); ++b) {
      Img2ImgParams alone = params;
      alone.strengths.clear();
      alone.strength = strengths[b];
      auto single = (*pipeline)->img2img(batch.slice(0, b, b + 1), {prompts[b]}, alone, {seeds[b]});
      ASSERT_TRUE(single.ok()) << single.status();
      test::expect_close((*mixed).slice(0, b, b + 1), *single, 1e-4,
                         absl::StrCat(kind, ": image ", b, " of the mixed batch"));
    }
    // The strengths are used: the same batch at one strength differs.
    params.strengths.clear();
    params.strength = 0.5;
    auto uniform = (*pipeline)->img2img(batch, prompts, params, seeds);
    ASSERT_TRUE(uniform.ok());
    EXPECT_GT(((*uniform).slice(0, 0, 1) - (*mixed).slice(0, 0, 1)).abs().max().item<double>(), 1e-3) << kind;
  }
}

TEST(SdxlPipelineTest, RejectsBadRequests) {
  auto pipeline = SdxlPipeline::load(test::sdxl_model_dir(), PipelineOptions{});
  ASSERT_TRUE(pipeline.ok()) << pipeline.status();
  const at::Tensor image = at::rand({1, 3, 8, 8});
  Img2ImgParams params;
  params.steps = 4;
  params.strength = 0.1;  // int(4 * 0.1) = 0 steps
  EXPECT_FALSE((*pipeline)->img2img(image, {"a"}, params, {1}).ok());
  params.strength = 0.5;
  EXPECT_FALSE((*pipeline)->img2img(at::rand({1, 3, 9, 8}), {"a"}, params, {1}).ok());
  EXPECT_FALSE((*pipeline)->img2img(image, {"a", "b"}, params, {1}).ok());
  params.strengths = {0.5, 0.5};  // two strengths for one image
  EXPECT_FALSE((*pipeline)->img2img(image, {"a"}, params, {1}).ok());
  params.strengths = {1.5};
  const auto out_of_range = (*pipeline)->img2img(image, {"a"}, params, {1});
  ASSERT_FALSE(out_of_range.ok());
  EXPECT_NE(out_of_range.status().message().find("1.5"), std::string::npos) << out_of_range.status();
  EXPECT_FALSE((*pipeline)->set_cuda_graphs(true).ok());  // CPU pipeline
}

class RandomModelTest : public test::TempDirTest {};

// The writer of random full-size models (for the speed benchmark), exercised with the tiny configs: the
// folder it writes must load as an SDXL pipeline and run.
TEST_F(RandomModelTest, WritesALoadableSdxlFolder) {
  const ModelFolder fixture = *ModelFolder::open(test::sdxl_model_dir());
  SdxlConfigs configs{*fixture.read_json("unet"), *fixture.read_json("vae"), *fixture.read_json("text_encoder"),
                      *fixture.read_json("text_encoder_2"), *fixture.read_json("scheduler", "scheduler_config.json")};
  ASSERT_TRUE(write_random_sdxl_model(dir_.string(), configs, 5, "float32").ok());
  auto pipeline = SdxlPipeline::load(dir_.string(), PipelineOptions{});
  ASSERT_TRUE(pipeline.ok()) << pipeline.status();
  Img2ImgParams params;
  params.steps = 2;
  params.strength = 1.0;
  auto out = (*pipeline)->img2img(at::rand({1, 3, 8, 8}), {"a fern"}, params, {1});
  ASSERT_TRUE(out.ok()) << out.status();
  EXPECT_TRUE(out->isfinite().all().item<bool>());
  // Same seed, same weights.
  const std::string again = (dir_ / "again").string();
  ASSERT_TRUE(write_random_sdxl_model(again, configs, 5, "float32").ok());
  auto a = read_safetensors((dir_ / "unet/diffusion_pytorch_model.safetensors").string());
  auto b = read_safetensors(again + "/unet/diffusion_pytorch_model.safetensors");
  EXPECT_TRUE(at::equal(a->at("conv_in.weight"), b->at("conv_in.weight")));
  EXPECT_FALSE(write_random_sdxl_model(again, configs, 5, "int8").ok());
}

TEST(RandomModelConfigTest, BaseConfigsDescribeTheFullSizeSdxl) {
  const SdxlConfigs base = SdxlConfigs::base();
  int64_t unet_parameters = 0;
  for (const auto& spec : UNet2DCondition::weight_specs(*UNetConfig::from_json(base.unet))) {
    int64_t n = 1;
    for (int64_t d : spec.shape) n *= d;
    unet_parameters += n;
  }
  EXPECT_EQ(unet_parameters, 2567463684);  // SDXL base 1.0's UNet
  EXPECT_TRUE(VaeConfig::from_json(base.vae).ok());
  EXPECT_TRUE(ClipTextConfig::from_json(base.text_encoder_2).ok());
  EXPECT_TRUE(SchedulerConfig::from_json(base.scheduler).ok());
}

}  // namespace
}  // namespace gaps::sdxl

// Stable Diffusion 2 inpainting against diffusers' StableDiffusionInpaintPipeline on the tiny fixture
// (tests/fixtures/sd2_inpaint_tiny, made by tests/scripts/make_inpaint_fixtures.py): SD2's UNet options
// (9 input channels, per-block attention_head_dim, linear projections, no added embedding), the gelu CLIP
// text encoder's last hidden state, and inpainting of two images with soft masks (binarised at 0.5),
// guidance 5 and a CPU generator seeded 1234: 2 DDIM steps, 2 Euler steps (strength 1), 3 of 4 DDIM steps
// (strength 0.75), one generator per image, and the folder's PNDM (skip_prk_steps) for 4 steps at
// strength 1 and 3 of 4 at strength 0.75. Tolerance: max abs diff <= 1e-4 of the reference's scale.
// float16 and bfloat16 on CUDA: gpu/sdxl_cuda_test.cpp.
#include <filesystem>
#include <map>

#include <ATen/ATen.h>
#include <gtest/gtest.h>
#include <nlohmann/json.hpp>

#include "diffusion_worker/sdxl/inpaint_pipeline.h"
#include "diffusion_worker/sdxl/model_folder.h"
#include "diffusion_worker/sdxl/unet.h"
#include "tests/sd2_inpaint_test_util.h"
#include "tests/sdxl_test_util.h"
#include "tests/test_util.h"

namespace gaps::sdxl {
namespace {

using test::sd2_fixture_dir;
using test::sd2_inpaint_setup;
using test::sd2_model_dir;
using test::sd2_prompts;
using test::sd2_reference;

nlohmann::json unet_json() {
  auto json = read_json_file(sd2_model_dir() + "/unet/config.json");
  EXPECT_TRUE(json.ok()) << json.status();
  return json.ok() ? *json : nlohmann::json{};
}

TEST(Sd2InpaintTest, ReadsSd2UNetConfig) {
  auto config = UNetConfig::from_json(unet_json());
  ASSERT_TRUE(config.ok()) << config.status();
  EXPECT_EQ(config->in_channels, 9);
  // SD2 names the head counts attention_head_dim (diffusers reads it as the number of heads).
  EXPECT_EQ(config->num_attention_heads, (std::vector<int64_t>{2, 4}));
  EXPECT_TRUE(config->use_linear_projection);
  EXPECT_TRUE(config->addition_embed_type.empty());
  EXPECT_EQ(config->cross_attention_dim, 32);
}

// The UNet options of stabilityai/stable-diffusion-2-inpainting at full size: the tensors it asks for.
TEST(Sd2InpaintTest, Sd2InpaintingUNetConfigAtFullSize) {
  const nlohmann::json j = {
      {"_class_name", "UNet2DConditionModel"},
      {"act_fn", "silu"},
      {"attention_head_dim", {5, 10, 20, 20}},
      {"block_out_channels", {320, 640, 1280, 1280}},
      {"center_input_sample", false},
      {"cross_attention_dim", 1024},
      {"down_block_types", {"CrossAttnDownBlock2D", "CrossAttnDownBlock2D", "CrossAttnDownBlock2D", "DownBlock2D"}},
      {"downsample_padding", 1},
      {"dual_cross_attention", false},
      {"flip_sin_to_cos", true},
      {"freq_shift", 0},
      {"in_channels", 9},
      {"layers_per_block", 2},
      {"mid_block_scale_factor", 1},
      {"norm_eps", 1e-05},
      {"norm_num_groups", 32},
      {"out_channels", 4},
      {"sample_size", 64},
      {"up_block_types", {"UpBlock2D", "CrossAttnUpBlock2D", "CrossAttnUpBlock2D", "CrossAttnUpBlock2D"}},
      {"use_linear_projection", true}};
  auto config = UNetConfig::from_json(j);
  ASSERT_TRUE(config.ok()) << config.status();
  EXPECT_EQ(config->num_attention_heads, (std::vector<int64_t>{5, 10, 20, 20}));  // 64 channels per head
  std::map<std::string, std::vector<int64_t>> shapes;
  int64_t parameters = 0;
  for (const TensorSpec& spec : UNet2DCondition::weight_specs(*config)) {
    shapes[spec.name] = spec.shape;
    int64_t n = 1;
    for (int64_t d : spec.shape) n *= d;
    parameters += n;
  }
  // diffusers 0.42.1's UNet2DConditionModel with this config has 686 tensors, 865,925,124 parameters.
  EXPECT_EQ(shapes.size(), 686u);
  EXPECT_EQ(parameters, 865925124);
  EXPECT_EQ(shapes.at("conv_in.weight"), (std::vector<int64_t>{320, 9, 3, 3}));
  EXPECT_EQ(shapes.at("down_blocks.0.attentions.0.proj_in.weight"), (std::vector<int64_t>{320, 320}));
  EXPECT_EQ(shapes.at("down_blocks.0.attentions.0.transformer_blocks.0.attn2.to_k.weight"),
            (std::vector<int64_t>{320, 1024}));
  EXPECT_EQ(shapes.at("up_blocks.3.attentions.2.transformer_blocks.0.attn2.to_v.weight"),
            (std::vector<int64_t>{320, 1024}));
  EXPECT_EQ(shapes.count("add_embedding.linear_1.weight"), 0u);
  EXPECT_EQ(shapes.count("down_blocks.3.attentions.0.proj_in.weight"), 0u);  // DownBlock2D: no attention
}

TEST(Sd2InpaintTest, RejectsUnsupportedUNetOptionsByName) {
  for (const auto& [key, value] :
       std::vector<std::pair<std::string, nlohmann::json>>{{"dual_cross_attention", true},
                                                           {"num_class_embeds", 10},
                                                           {"act_fn", "gelu"},
                                                           {"center_input_sample", true},
                                                           {"mid_block_scale_factor", 2},
                                                           {"attention_type", "gated"},
                                                           {"conv_in_kernel", 5},
                                                           {"time_embedding_act_fn", "silu"},
                                                           {"resnet_out_scale_factor", 2.0}}) {
    nlohmann::json j = unet_json();
    j[key] = value;
    auto config = UNetConfig::from_json(j);
    ASSERT_FALSE(config.ok()) << key;
    EXPECT_TRUE(test::contains_all(std::string(config.status().message()), {key, "not supported"}));
  }
  // Defaults written out (as diffusers' configs do) are accepted, integer or float.
  nlohmann::json j = unet_json();
  j["mid_block_scale_factor"] = 1.0;
  j["resnet_out_scale_factor"] = 1;
  EXPECT_TRUE(UNetConfig::from_json(j).ok());
}

TEST(Sd2InpaintTest, UNetMatchesDiffusers) {
  auto config = UNetConfig::from_json(unet_json());
  ASSERT_TRUE(config.ok()) << config.status();
  auto weights = read_folder_weights(sd2_model_dir() + "/unet");
  ASSERT_TRUE(weights.ok()) << weights.status();
  auto unet = UNet2DCondition::load(*config, *weights, at::TensorOptions(), "unet");
  ASSERT_TRUE(unet.ok()) << unet.status();
  const TensorMap ref = sd2_reference("unet");
  UNetInputs in;
  in.sample = ref.at("sample");
  in.timestep = ref.at("timestep");
  in.encoder_hidden_states = ref.at("encoder_hidden_states");
  test::expect_close(unet->forward(in), ref.at("out"), 1e-4, "SD2 inpainting UNet");
}

// Runs the recorded inputs of reference `name` and compares with diffusers' output.
void expect_run_matches(InpaintPipeline& pipeline, const std::string& name, const std::vector<uint64_t>& seeds) {
  const nlohmann::json& run = sd2_inpaint_setup()["runs"][name];
  const TensorMap ref = sd2_reference("inpaint_" + name);
  InpaintParams params;
  params.steps = run["steps"].get<int64_t>();
  params.strength = run["strength"].get<double>();
  params.guidance_scale = sd2_inpaint_setup()["guidance_scale"].get<double>();
  auto out = pipeline.inpaint(ref.at("image"), ref.at("mask"), sd2_prompts(), params, seeds);
  ASSERT_TRUE(out.ok()) << out.status();
  test::expect_close(*out, ref.at("out"), 1e-4, "inpainting " + name);
}

class Sd2InpaintPipelineTest : public ::testing::Test {
 protected:
  static std::unique_ptr<InpaintPipeline> load(const std::string& scheduler = "") {
    InpaintPipelineOptions options;
    options.scheduler = scheduler;
    auto pipeline = InpaintPipeline::load(sd2_model_dir(), options);
    EXPECT_TRUE(pipeline.ok()) << pipeline.status();
    return pipeline.ok() ? *std::move(pipeline) : nullptr;
  }
};

TEST_F(Sd2InpaintPipelineTest, PromptEmbeddingsAreTheLastHiddenState) {
  auto pipeline = load();
  ASSERT_NE(pipeline, nullptr);
  const TensorMap ref = sd2_reference("prompt_embeds");
  test::expect_close(pipeline->encode_prompts(sd2_prompts()), ref.at("cond"), 1e-4, "prompt embeddings");
  test::expect_close(pipeline->encode_prompts({"", ""}), ref.at("uncond"), 1e-4, "empty-prompt embeddings");
}

TEST_F(Sd2InpaintPipelineTest, DdimFromNoiseMatchesDiffusers) {
  auto pipeline = load();
  ASSERT_NE(pipeline, nullptr);
  expect_run_matches(*pipeline, "ddim", {sd2_inpaint_setup()["seed"].get<uint64_t>()});
  // Another seed gives another image (the draws are used).
  const TensorMap ref = sd2_reference("inpaint_ddim");
  InpaintParams params;
  params.steps = 2;
  params.guidance_scale = 5.0;
  auto other = pipeline->inpaint(ref.at("image"), ref.at("mask"), sd2_prompts(), params, {99});
  ASSERT_TRUE(other.ok()) << other.status();
  EXPECT_GT((*other - ref.at("out")).abs().max().item<double>(), 1e-3);
}

TEST_F(Sd2InpaintPipelineTest, EulerFromNoiseMatchesDiffusers) {
  auto pipeline = load("euler");
  ASSERT_NE(pipeline, nullptr);
  expect_run_matches(*pipeline, "euler", {sd2_inpaint_setup()["seed"].get<uint64_t>()});
}

TEST_F(Sd2InpaintPipelineTest, PartialStrengthMatchesDiffusers) {
  auto pipeline = load();
  ASSERT_NE(pipeline, nullptr);
  expect_run_matches(*pipeline, "ddim_strength", {sd2_inpaint_setup()["seed"].get<uint64_t>()});
}

TEST_F(Sd2InpaintPipelineTest, OneSeedPerImageMatchesDiffusersGeneratorList) {
  auto pipeline = load();
  ASSERT_NE(pipeline, nullptr);
  expect_run_matches(*pipeline, "seed_list",
                     sd2_inpaint_setup()["runs"]["seed_list"]["seeds"].get<std::vector<uint64_t>>());
}

TEST_F(Sd2InpaintPipelineTest, RejectsBadRequests) {
  auto pipeline = load();
  ASSERT_NE(pipeline, nullptr);
  const at::Tensor images = at::rand({2, 3, 16, 16});
  const at::Tensor masks = at::zeros({2, 1, 16, 16});
  InpaintParams params;
  params.steps = 2;
  const auto error = [&](const at::Tensor& i, const at::Tensor& m, const std::vector<std::string>& p,
                         const InpaintParams& q, const std::vector<uint64_t>& s) {
    auto out = pipeline->inpaint(i, m, p, q, s);
    EXPECT_FALSE(out.ok());
    return out.ok() ? std::string() : std::string(out.status().message());
  };
  EXPECT_TRUE(
      test::contains_all(error(images, at::zeros({2, 16, 16}), {"x"}, params, {1}), {"masks", "B x 1 x H x W"}));
  EXPECT_TRUE(test::contains_all(error(images, at::zeros({1, 1, 16, 16}), {"x"}, params, {1}), {"masks"}));
  EXPECT_TRUE(test::contains_all(error(at::rand({1, 3, 15, 16}), at::zeros({1, 1, 15, 16}), {"x"}, params, {1}),
                                 {"not a multiple of"}));
  EXPECT_TRUE(test::contains_all(error(images, masks, {"a", "b", "c"}, params, {1}), {"prompt"}));
  EXPECT_TRUE(test::contains_all(error(images, masks, {"x"}, params, {1, 2, 3}), {"seed"}));
  InpaintParams bad = params;
  bad.strength = 0;
  EXPECT_TRUE(test::contains_all(error(images, masks, {"x"}, bad, {1}), {"strength"}));
  bad.strength = 0.2;  // int(2 * 0.2) = 0 steps
  EXPECT_TRUE(test::contains_all(error(images, masks, {"x"}, bad, {1}), {"no step"}));
  bad = params;
  bad.negative_prompts = {"a", "b", "c"};
  EXPECT_TRUE(test::contains_all(error(images, masks, {"x"}, bad, {1}), {"negative prompt"}));
}

TEST(Sd2InpaintLoadTest, RejectsAUNetWithoutMaskInputs) {
  // The SDXL fixture's UNet takes 4 channels and text_time conditioning.
  auto pipeline = InpaintPipeline::load(test::sdxl_model_dir(), InpaintPipelineOptions{});
  ASSERT_FALSE(pipeline.ok());
  EXPECT_TRUE(test::contains_all(std::string(pipeline.status().message()),
                                 {"not an inpainting UNet", "in_channels 9", "in_channels 4"}));
}

TEST(Sd2InpaintLoadTest, RejectsAnUnimplementedSchedulerByName) {
  InpaintPipelineOptions options;
  options.scheduler = "lms";
  auto pipeline = InpaintPipeline::load(sd2_model_dir(), options);
  ASSERT_FALSE(pipeline.ok());
  EXPECT_TRUE(test::contains_all(std::string(pipeline.status().message()), {"scheduler", "lms"}));
}

// The SD2 inpainting repository ships a PNDMScheduler with skip_prk_steps: here the fixture's DDIM settings
// under that class name, as diffusers' PNDMScheduler.from_config(..., skip_prk_steps=True) recorded them.
class Sd2InpaintPndmTest : public test::TempDirTest {
 protected:
  std::string pndm_folder(bool skip_prk_steps) {
    const std::filesystem::path model = dir_ / (skip_prk_steps ? "model" : "model_prk");
    std::filesystem::copy(sd2_model_dir(), model, std::filesystem::copy_options::recursive);
    auto json = read_json_file((model / "scheduler" / "scheduler_config.json").string());
    EXPECT_TRUE(json.ok()) << json.status();
    (*json)["_class_name"] = "PNDMScheduler";
    (*json)["skip_prk_steps"] = skip_prk_steps;
    std::filesystem::remove(model / "scheduler" / "scheduler_config.json");
    write(model.filename().string() + "/scheduler/scheduler_config.json", json->dump());
    return model.string();
  }
};

TEST_F(Sd2InpaintPndmTest, TheFoldersPndmMatchesDiffusersFromNoiseAndPartWay) {
  auto pipeline = InpaintPipeline::load(pndm_folder(true), InpaintPipelineOptions{});
  ASSERT_TRUE(pipeline.ok()) << pipeline.status();
  const auto seed = sd2_inpaint_setup()["seed"].get<uint64_t>();
  expect_run_matches(**pipeline, "pndm", {seed});
  expect_run_matches(**pipeline, "pndm_strength", {seed});
}

TEST_F(Sd2InpaintPndmTest, RungeKuttaWarmUpIsRefusedAndANamedSchedulerReplacesIt) {
  auto refused = InpaintPipeline::load(pndm_folder(false), InpaintPipelineOptions{});
  ASSERT_FALSE(refused.ok());
  EXPECT_TRUE(test::contains_all(std::string(refused.status().message()), {"scheduler", "skip_prk_steps"}));
  InpaintPipelineOptions options;
  options.scheduler = "ddim";
  auto pipeline = InpaintPipeline::load(pndm_folder(true), options);
  ASSERT_TRUE(pipeline.ok()) << pipeline.status();
  expect_run_matches(**pipeline, "ddim", {sd2_inpaint_setup()["seed"].get<uint64_t>()});
}

}  // namespace
}  // namespace gaps::sdxl

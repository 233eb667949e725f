// IP-Adapter against diffusers/transformers on tiny random weights (tests/fixtures/ip_adapter_tiny, made
// by tests/scripts/make_ip_adapter_fixtures.py for the UNet of tests/fixtures/sdxl_tiny): CLIP image
// preprocessing and CLIPVisionModelWithProjection, the image projection (and of zeros, the negative
// prompt), one UNet forward with decoupled cross-attention at scale 0.5 (a different reference per image),
// and img2img of two images with one reference image (2 of 4 Euler steps, guidance 5, seed 1234). fp32
// on the CPU; tolerance: max abs diff <= 1e-4 x max(1, max |reference|), as the other SDXL parity suites.
// Also the errors (missing tensors, layer counts, inconsistent options) and the `sdxl` backend's use of
// the nearest reference view. float16 and CUDA-graph replay: gpu/sdxl_cuda_test.cpp.
#include <fstream>

#include <ATen/ATen.h>
#include <gtest/gtest.h>
#include <nlohmann/json.hpp>

#include "diffusion_worker/backend_registry.h"
#include "diffusion_worker/sdxl/clip_vision_encoder.h"
#include "diffusion_worker/sdxl/ip_adapter.h"
#include "diffusion_worker/sdxl/model_folder.h"
#include "diffusion_worker/sdxl/pipeline.h"
#include "diffusion_worker/sdxl/unet.h"
#include "tests/ip_adapter_test_util.h"
#include "tests/sdxl_test_util.h"

namespace gaps::sdxl {
namespace {

constexpr double kTolerance = 1e-4;
using test::contains_all;
using test::expect_close;
using test::image_encoder_dir;
using test::ip_dir;
using test::ip_options;
using test::ip_reference;
using test::ip_weights;

UNet2DCondition tiny_unet() {
  auto folder = ModelFolder::open(test::sdxl_model_dir());
  EXPECT_TRUE(folder.ok()) << folder.status();
  auto unet = UNet2DCondition::load(*UNetConfig::from_json(*folder->read_json("unet")), *folder->read_weights("unet"),
                                    at::TensorOptions(), "unet");
  EXPECT_TRUE(unet.ok()) << unet.status();
  return *std::move(unet);
}

TEST(ClipVisionEncoderTest, MatchesCLIPImageProcessorAndCLIPVisionModelWithProjection) {
  auto encoder = ClipVisionEncoder::load_folder(image_encoder_dir(), at::TensorOptions());
  ASSERT_TRUE(encoder.ok()) << encoder.status();
  const TensorMap ref = ip_reference("encoder");
  for (const char* i : {"0", "1"}) {  // 48 x 64: shortest side to 32 and center crop; 40 x 40: resize only
    auto pixels = encoder->preprocess(ref.at(std::string("image_") + i));
    ASSERT_TRUE(pixels.ok()) << pixels.status();
    expect_close(*pixels, ref.at(std::string("pixel_values_") + i), kTolerance, std::string("pixel_values ") + i);
  }
  auto embeds = encoder->embed({ref.at("image_0"), ref.at("image_1")});
  ASSERT_TRUE(embeds.ok()) << embeds.status();
  expect_close(*embeds, ref.at("image_embeds"), kTolerance, "image_embeds");
  const at::Tensor pixels = at::cat({*encoder->preprocess(ref.at("image_0")), *encoder->preprocess(ref.at("image_1"))});
  expect_close(encoder->forward(pixels).last_hidden_state, ref.at("last_hidden_state"), kTolerance,
               "last_hidden_state");
  EXPECT_FALSE(encoder->preprocess(at::rand({8, 8})).ok());
}

TEST(ClipVisionEncoderTest, MissingTensorIsNamed) {
  auto weights = read_folder_weights(image_encoder_dir());
  ASSERT_TRUE(weights.ok()) << weights.status();
  weights->erase("vision_model.post_layernorm.weight");
  const auto config = ClipVisionConfig::from_json(*read_json_file(image_encoder_dir() + "/config.json"));
  ASSERT_TRUE(config.ok()) << config.status();
  auto encoder = ClipVisionEncoder::load(*config, *weights, at::TensorOptions(), "encoder");
  ASSERT_FALSE(encoder.ok());
  EXPECT_TRUE(contains_all(std::string(encoder.status().message()), {"missing", "vision_model.post_layernorm.weight"}));
}

TEST(IpAdapterTest, ProjectsImageEmbeddingsAsDiffusers) {
  UNet2DCondition unet = tiny_unet();
  auto adapter = IpAdapter::load(ip_weights(), unet, at::TensorOptions());
  ASSERT_TRUE(adapter.ok()) << adapter.status();
  EXPECT_EQ((*adapter)->num_layers(), 12);  // down block 1: 2 x 2, up block 0: 3 x 2, mid: 2
  const TensorMap ref = ip_reference("projection");
  expect_close((*adapter)->project(ref.at("image_embeds")), ref.at("tokens"), kTolerance, "image tokens");
  expect_close((*adapter)->project(at::zeros_like(ref.at("image_embeds"))), ref.at("negative_tokens"), kTolerance,
               "negative image tokens");
}

TEST(IpAdapterTest, UNetWithDecoupledCrossAttentionMatchesDiffusers) {
  UNet2DCondition unet = tiny_unet();
  const TensorMap ref = ip_reference("unet");
  const UNetInputs in = test::recorded_unet_inputs(ref);
  const at::Tensor plain = unet.forward(in);
  auto adapter = IpAdapter::load(ip_weights(), unet, at::TensorOptions());
  ASSERT_TRUE(adapter.ok()) << adapter.status();
  const at::Tensor tokens = (*adapter)->project(ref.at("image_embeds"));
  (*adapter)->set_image_prompt(tokens, at::full({2}, 0.5));
  expect_close(unet.forward(in), ref.at("out"), kTolerance, "UNet output with IP-Adapter");
  // Scale 0 is the plain UNet; a per-image scale applies to its own image only.
  (*adapter)->set_image_prompt(tokens, at::zeros({2}));
  expect_close(unet.forward(in), plain, 1e-6, "UNet output at scale 0");
  (*adapter)->set_image_prompt(tokens, at::tensor({0.5f, 0.0f}));
  const at::Tensor mixed = unet.forward(in);
  expect_close(mixed[0], ref.at("out")[0], kTolerance, "image 0 at scale 0.5");
  expect_close(mixed[1], plain[1], 1e-6, "image 1 at scale 0");
}

TEST(IpAdapterTest, MissingTensorIsNamedAndTheUNetIsLeftAlone) {
  UNet2DCondition unet = tiny_unet();
  const TensorMap ref = ip_reference("unet");
  const at::Tensor plain = unet.forward(test::recorded_unet_inputs(ref));
  auto weights = read_safetensors(ip_weights());
  ASSERT_TRUE(weights.ok());
  TensorMap missing = *weights;
  missing.erase("image_proj.norm.bias");
  missing.erase("ip_adapter.5.to_v_ip.weight");
  missing.emplace("ip_adapter.5.to_q_ip.weight", at::zeros({32, 64}));  // keeps 12 layer numbers
  auto adapter = IpAdapter::load(missing, unet, at::TensorOptions(), "ip.safetensors");
  ASSERT_FALSE(adapter.ok());
  EXPECT_TRUE(contains_all(std::string(adapter.status().message()),
                           {"ip.safetensors", "missing", "image_proj.norm.bias", "ip_adapter.5.to_v_ip.weight",
                            "unexpected", "ip_adapter.5.to_q_ip.weight"}));
  EXPECT_TRUE(at::equal(unet.forward(test::recorded_unet_inputs(ref)), plain));
}

TEST(IpAdapterTest, LayerCountMismatchIsNamed) {
  UNet2DCondition unet = tiny_unet();
  auto weights = read_safetensors(ip_weights());
  ASSERT_TRUE(weights.ok());
  TensorMap fewer = *weights;
  fewer.erase("ip_adapter.23.to_k_ip.weight");
  fewer.erase("ip_adapter.23.to_v_ip.weight");
  auto adapter = IpAdapter::load(fewer, unet, at::TensorOptions(), "ip.safetensors");
  ASSERT_FALSE(adapter.ok());
  EXPECT_TRUE(contains_all(std::string(adapter.status().message()),
                           {"ip.safetensors", "11 cross-attention layers", "the UNet has 12"}));
  // A layer of the wrong width (weights of another UNet) is named with both shapes.
  TensorMap wider = *weights;
  wider["ip_adapter.1.to_k_ip.weight"] = at::zeros({64, 64});
  adapter = IpAdapter::load(wider, unet, at::TensorOptions(), "ip.safetensors");
  ASSERT_FALSE(adapter.ok());
  EXPECT_TRUE(contains_all(std::string(adapter.status().message()), {"mis-shaped", "ip_adapter.1.to_k_ip.weight"}));
  // IP-Adapter Plus checkpoints are refused by name.
  TensorMap plus = *weights;
  plus.emplace("image_proj.latents", at::zeros({1, 16, 64}));
  adapter = IpAdapter::load(plus, unet, at::TensorOptions(), "ip.safetensors");
  ASSERT_FALSE(adapter.ok());
  EXPECT_TRUE(contains_all(std::string(adapter.status().message()), {"image_proj.latents", "Plus"}));
}

TEST(IpAdapterPipelineTest, Img2ImgWithReferenceImagesMatchesDiffusers) {
  std::ifstream in(ip_dir() + "/reference/img2img.json");
  const nlohmann::json setup = nlohmann::json::parse(in);
  auto pipeline = SdxlPipeline::load(test::sdxl_model_dir(), ip_options());
  ASSERT_TRUE(pipeline.ok()) << pipeline.status();
  ASSERT_NE((*pipeline)->ip_adapter(), nullptr);
  const TensorMap ref = ip_reference("img2img");
  const TensorMap images = ip_reference("encoder");
  Img2ImgParams params;
  params.strength = setup["strength"].get<double>();
  params.steps = setup["num_inference_steps"].get<int64_t>();
  params.guidance_scale = setup["guidance_scale"].get<double>();
  // diffusers repeats its one image prompt for every image of the batch.
  params.reference_images = {images.at("image_0"), images.at("image_0")};
  params.ip_adapter_scales = {setup["ip_adapter_scale"].get<double>()};
  const auto prompts = setup["prompts"].get<std::vector<std::string>>();
  const uint64_t seed = setup["seed"].get<uint64_t>();
  auto out = (*pipeline)->img2img(ref.at("image"), prompts, params, {seed});
  ASSERT_TRUE(out.ok()) << out.status();
  test::expect_close(*out, ref.at("out"), kTolerance, "img2img output with IP-Adapter");
  // Without reference images the adapter adds nothing: the result is plain img2img's, which differs.
  params.reference_images.clear();
  auto without = (*pipeline)->img2img(ref.at("image"), prompts, params, {seed});
  ASSERT_TRUE(without.ok()) << without.status();
  auto plain_pipeline = SdxlPipeline::load(test::sdxl_model_dir(), PipelineOptions{});
  ASSERT_TRUE(plain_pipeline.ok());
  auto plain = (*plain_pipeline)->img2img(ref.at("image"), prompts, params, {seed});
  ASSERT_TRUE(plain.ok());
  test::expect_close(*without, *plain, 1e-6, "img2img without reference images");
  EXPECT_GT((*without - *out).abs().max().item<double>(), 1e-3);
}

TEST(IpAdapterPipelineTest, RejectsInconsistentOptionsAndRequests) {
  PipelineOptions half = ip_options();
  half.image_encoder.clear();
  EXPECT_FALSE(SdxlPipeline::load(test::sdxl_model_dir(), half).ok());
  auto plain = SdxlPipeline::load(test::sdxl_model_dir(), PipelineOptions{});
  ASSERT_TRUE(plain.ok());
  Img2ImgParams params;
  params.steps = 2;
  params.strength = 1.0;
  params.reference_images = {at::rand({16, 16, 3})};
  auto refused = (*plain)->img2img(at::rand({1, 3, 8, 8}), {"a"}, params, {1});
  ASSERT_FALSE(refused.ok());
  EXPECT_TRUE(contains_all(std::string(refused.status().message()), {"IP-Adapter"}));

  auto pipeline = SdxlPipeline::load(test::sdxl_model_dir(), ip_options());
  ASSERT_TRUE(pipeline.ok()) << pipeline.status();
  params.reference_images = {at::rand({16, 16, 3}), at::rand({16, 16, 3})};  // two for one image
  EXPECT_FALSE((*pipeline)->img2img(at::rand({1, 3, 8, 8}), {"a"}, params, {1}).ok());
  params.reference_images = {at::rand({16, 16})};  // not H x W x 3
  EXPECT_FALSE((*pipeline)->img2img(at::rand({1, 3, 8, 8}), {"a"}, params, {1}).ok());
  params.reference_images = {at::rand({16, 16, 3})};
  params.ip_adapter_scales = {0.5, 0.5};  // two scales for one image
  EXPECT_FALSE((*pipeline)->img2img(at::rand({1, 3, 8, 8}), {"a"}, params, {1}).ok());
}

// The `sdxl` backend with an IP-Adapter: the nearest reference view of each request is its image prompt.
TEST(SdxlGeneratorIpAdapterTest, NearestReferenceViewIsTheImagePrompt) {
  const std::string ip =
      ", \"ip_adapter\": \"" + ip_weights() + "\", \"image_encoder\": \"" + image_encoder_dir() + "\"";
  const std::string base = "{\"weights\": \"" + test::sdxl_model_dir() + "\", \"steps\": 4, \"prompt\": \"a fern\"";
  auto generator = make_generator("sdxl", base + ip + ", \"ip_adapter_scale\": 0.7}");
  ASSERT_TRUE(generator.ok()) << generator.status();
  GenerationRequest with_refs;
  with_refs.render_rgb = at::rand({8, 6, 3});
  with_refs.strength = 0.5;
  with_refs.seed = 3;
  ReferenceView nearest, farther;
  nearest.image = at::rand({12, 16, 3});
  farther.image = at::rand({12, 16, 3});
  with_refs.references = {nearest, farther};
  GenerationRequest without_refs = with_refs;
  without_refs.references.clear();
  auto images = (*generator)->generate({with_refs, without_refs});
  ASSERT_TRUE(images.ok()) << images.status();

  auto pipeline = SdxlPipeline::load(test::sdxl_model_dir(), ip_options());
  ASSERT_TRUE(pipeline.ok()) << pipeline.status();
  Img2ImgParams params;
  params.steps = 4;
  params.reference_images = {nearest.image};
  params.ip_adapter_scales = {0.7};
  const at::Tensor render = with_refs.render_rgb.permute({2, 0, 1}).unsqueeze(0);
  auto direct = (*pipeline)->img2img(render, {"a fern"}, params, {3});
  ASSERT_TRUE(direct.ok()) << direct.status();
  expect_close((*images)[0], (*direct)[0].permute({1, 2, 0}), 1e-5, "generator vs pipeline with the nearest view");
  params.reference_images.clear();
  auto plain = (*pipeline)->img2img(render, {"a fern"}, params, {3});
  ASSERT_TRUE(plain.ok()) << plain.status();
  expect_close((*images)[1], (*plain)[0].permute({1, 2, 0}), 1e-5, "generator without reference views");
  EXPECT_GT(((*images)[0] - (*images)[1]).abs().max().item<double>(), 1e-3);

  auto half = make_generator("sdxl", base + ", \"ip_adapter\": \"" + ip_weights() + "\"}");
  ASSERT_FALSE(half.ok());
  EXPECT_TRUE(contains_all(std::string(half.status().message()), {"image_encoder"}));
  auto bad_scale = make_generator("sdxl", base + ip + ", \"ip_adapter_scale\": \"high\"}");
  ASSERT_FALSE(bad_scale.ok());
  EXPECT_TRUE(contains_all(std::string(bad_scale.status().message()), {"ip_adapter_scale"}));
}

// A request's ip_adapter_scale (the trainer sends GapsConfig's lambda_ip) wins over the option, which serves
// requests without one; requests of one batch may differ.
TEST(SdxlGeneratorIpAdapterTest, TheRequestsScaleWinsOverTheOption) {
  const std::string options = "{\"weights\": \"" + test::sdxl_model_dir() +
                              "\", \"steps\": 4, \"prompt\": \"a fern\", " + "\"ip_adapter\": \"" + ip_weights() +
                              "\", \"image_encoder\": \"" + image_encoder_dir() + "\", \"ip_adapter_scale\": 0.7}";
  auto generator = make_generator("sdxl", options);
  ASSERT_TRUE(generator.ok()) << generator.status();
  GenerationRequest scaled;
  scaled.render_rgb = at::rand({8, 6, 3});
  scaled.strength = 0.5;
  scaled.seed = 3;
  ReferenceView nearest;
  nearest.image = at::rand({12, 16, 3});
  scaled.references = {nearest};
  scaled.ip_adapter_scale = 0.2;
  GenerationRequest unscaled = scaled;
  unscaled.ip_adapter_scale.reset();
  auto images = (*generator)->generate({scaled, unscaled});
  ASSERT_TRUE(images.ok()) << images.status();
  EXPECT_TRUE((*generator)->notes().empty());

  auto pipeline = SdxlPipeline::load(test::sdxl_model_dir(), ip_options());
  ASSERT_TRUE(pipeline.ok()) << pipeline.status();
  const at::Tensor render = scaled.render_rgb.permute({2, 0, 1}).unsqueeze(0);
  for (const auto& [k, scale] : {std::pair<int, double>{0, 0.2}, {1, 0.7}}) {
    Img2ImgParams params;
    params.steps = 4;
    params.reference_images = {nearest.image};
    params.ip_adapter_scales = {scale};
    auto direct = (*pipeline)->img2img(render, {"a fern"}, params, {3});
    ASSERT_TRUE(direct.ok()) << direct.status();
    expect_close((*images)[k], (*direct)[0].permute({1, 2, 0}), 1e-5, "request " + std::to_string(k));
  }
  scaled.ip_adapter_scale = -1;
  const absl::Status refused = (*generator)->generate({scaled}).status();
  EXPECT_TRUE(contains_all(std::string(refused.message()), {"request 0", "ip_adapter_scale"})) << refused;
}

}  // namespace
}  // namespace gaps::sdxl

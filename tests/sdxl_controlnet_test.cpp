// SDXL ControlNet against diffusers on the tiny fixtures (tests/fixtures/sdxl_controlnet_tiny, made by
// tests/scripts/make_controlnet_fixtures.py from the tiny SDXL model of tests/fixtures/sdxl_tiny): the
// ControlNetModel's residuals, the UNet with them, and StableDiffusionXLControlNetImg2ImgPipeline (2 of 4
// Euler steps, guidance 5, conditioning scale 0.8, seed 1234). fp32 on the CPU (weights stored in fp16);
// tolerance as the other sdxl suites: max abs diff <= 1e-4 x max(1, max |reference|). Also: loading errors
// name the tensor, the depth conditioning image of a render by hand-computed values, the sdxl backend
// with a ControlNet. float16 and CUDA-graph replay with residuals: gpu/sdxl_cuda_test.cpp.
#include <filesystem>
#include <fstream>

#include <ATen/ATen.h>
#include <gtest/gtest.h>
#include <nlohmann/json.hpp>

#include "diffusion_worker/backend_registry.h"
#include "diffusion_worker/depth_control.h"
#include "diffusion_worker/sdxl/controlnet.h"
#include "diffusion_worker/sdxl/model_folder.h"
#include "diffusion_worker/sdxl/pipeline.h"
#include "diffusion_worker/sdxl/unet.h"
#include "tests/controlnet_test_util.h"
#include "tests/sdxl_test_util.h"
#include "tests/test_util.h"

namespace gaps {
namespace {

using sdxl::TensorMap;
using test::contains_all;
using test::controlled_run;
using test::ControlledRun;
using test::controlnet_dir;
using test::controlnet_reference;
using test::expect_close;

constexpr double kTolerance = 1e-4;

TEST(ControlNetTest, ResidualsMatchDiffusers) {
  auto net = sdxl::ControlNet::load_folder(controlnet_dir(), at::TensorOptions().dtype(at::kFloat));
  ASSERT_TRUE(net.ok()) << net.status();
  EXPECT_EQ(net->config().downscale(), 2);
  const TensorMap ref = controlnet_reference("controlnet");
  const sdxl::ControlNetResiduals out =
      net->forward(test::recorded_unet_inputs(ref), ref.at("controlnet_cond"), ref.at("conditioning_scale"));
  ASSERT_EQ(out.down.size(), 6u);
  for (size_t i = 0; i < out.down.size(); ++i) {
    expect_close(out.down[i], ref.at("down_" + std::to_string(i)), kTolerance, "down residual " + std::to_string(i));
  }
  expect_close(out.mid, ref.at("mid"), kTolerance, "mid residual");
  // The scale multiplies every residual (per batch entry): scale 0 gives zeros.
  const sdxl::ControlNetResiduals off =
      net->forward(test::recorded_unet_inputs(ref), ref.at("controlnet_cond"), at::zeros({2}));
  EXPECT_EQ(off.mid.abs().max().item<double>(), 0.0);
}

TEST(ControlNetTest, UNetWithResidualsMatchesDiffusers) {
  auto folder = sdxl::ModelFolder::open(test::sdxl_model_dir());
  ASSERT_TRUE(folder.ok());
  auto unet = sdxl::UNet2DCondition::load(*sdxl::UNetConfig::from_json(*folder->read_json("unet")),
                                          *folder->read_weights("unet"), at::TensorOptions(), "unet");
  ASSERT_TRUE(unet.ok()) << unet.status();
  const TensorMap ref = controlnet_reference("controlnet");
  sdxl::UNetInputs in = test::recorded_unet_inputs(ref);
  for (int i = 0; i < 6; ++i) in.down_block_residuals.push_back(ref.at("down_" + std::to_string(i)));
  in.mid_block_residual = ref.at("mid");
  const at::Tensor expected = controlnet_reference("unet_controlled").at("out");
  expect_close(unet->forward(in), expected, kTolerance, "UNet with ControlNet residuals");
  // The residuals matter: without them the output is another one.
  EXPECT_GT((unet->forward(test::recorded_unet_inputs(ref)) - expected).abs().max().item<double>(), 1e-2);
}

TEST(ControlNetPipelineTest, Img2ImgMatchesDiffusers) {
  sdxl::PipelineOptions options;
  options.controlnet = controlnet_dir();
  auto pipeline = sdxl::SdxlPipeline::load(test::sdxl_model_dir(), options);
  ASSERT_TRUE(pipeline.ok()) << pipeline.status();
  ASSERT_NE((*pipeline)->controlnet(), nullptr);
  const ControlledRun run = controlled_run();
  const auto prompts = run.setup["prompts"].get<std::vector<std::string>>();
  const uint64_t seed = run.setup["seed"].get<uint64_t>();
  const double scale = run.setup["controlnet_conditioning_scale"].get<double>();
  auto out = (*pipeline)->img2img(run.ref.at("image"), prompts, run.params, {seed},
                                  sdxl::ControlInput{run.ref.at("control_image"), {scale}});
  ASSERT_TRUE(out.ok()) << out.status();
  expect_close(*out, run.ref.at("out"), kTolerance, "ControlNet img2img output");
  // One scale per image gives the same; scale 0 gives plain img2img, which differs from the controlled one.
  auto per_image = (*pipeline)->img2img(run.ref.at("image"), prompts, run.params, {seed},
                                        sdxl::ControlInput{run.ref.at("control_image"), {scale, scale}});
  ASSERT_TRUE(per_image.ok());
  expect_close(*per_image, *out, 1e-6, "per-image scales");
  auto zero = (*pipeline)->img2img(run.ref.at("image"), prompts, run.params, {seed},
                                   sdxl::ControlInput{run.ref.at("control_image"), {0.0}});
  auto plain = (*pipeline)->img2img(run.ref.at("image"), prompts, run.params, {seed});
  ASSERT_TRUE(zero.ok() && plain.ok());
  EXPECT_TRUE(at::equal(*zero, *plain));
  EXPECT_GT((*plain - *out).abs().max().item<double>(), 1e-3);
}

// Convolutions and activations in channels-last order compute the same images (the UNet, the ControlNet and
// the VAE all convolve here; ATen's GroupNorm on the CPU, the fused kernel's parity is gpu/sdxl_cuda_test.cpp's).
TEST(ControlNetPipelineTest, ChannelsLastMatchesDiffusers) {
  sdxl::PipelineOptions options;
  options.controlnet = controlnet_dir();
  options.channels_last = true;
  auto pipeline = sdxl::SdxlPipeline::load(test::sdxl_model_dir(), options);
  ASSERT_TRUE(pipeline.ok()) << pipeline.status();
  const ControlledRun run = controlled_run();
  auto out = (*pipeline)->img2img(
      run.ref.at("image"), run.setup["prompts"].get<std::vector<std::string>>(), run.params,
      {run.setup["seed"].get<uint64_t>()},
      sdxl::ControlInput{run.ref.at("control_image"), {run.setup["controlnet_conditioning_scale"].get<double>()}});
  ASSERT_TRUE(out.ok()) << out.status();
  expect_close(*out, run.ref.at("out"), kTolerance, "channels-last ControlNet img2img output");
  // The activations take the model's layout whatever the input's (1x1 kernels included: their strides are NCHW's too).
  const at::Tensor images = run.ref.at("image") * 2 - 1;
  for (const at::Tensor& input : {images, images.contiguous(at::MemoryFormat::ChannelsLast)}) {
    const at::Tensor moments = (*pipeline)->vae().encode_moments(input);
    EXPECT_TRUE(moments.is_contiguous(at::MemoryFormat::ChannelsLast) && !moments.is_contiguous());
    EXPECT_TRUE(
        (*pipeline)->vae().decode(moments.slice(1, 0, 4).contiguous()).is_contiguous(at::MemoryFormat::ChannelsLast));
  }
}

// An NCHW model keeps NCHW activations whatever the input's layout (on a GPU a channels-last activation would
// take the other GroupNorm kernel). The channels-last model's layout on CUDA: gpu/sdxl_cuda_test.cpp.
TEST(ControlNetPipelineTest, AnNchwModelKeepsNchwActivations) {
  auto pipeline = sdxl::SdxlPipeline::load(test::sdxl_model_dir(), sdxl::PipelineOptions{});
  ASSERT_TRUE(pipeline.ok()) << pipeline.status();
  const at::Tensor images = controlled_run().ref.at("image") * 2 - 1;
  for (const at::Tensor& input : {images, images.contiguous(at::MemoryFormat::ChannelsLast)}) {
    const at::Tensor moments = (*pipeline)->vae().encode_moments(input);
    EXPECT_TRUE(moments.is_contiguous());
    EXPECT_TRUE(
        (*pipeline)->vae().decode(moments.slice(1, 0, 4).contiguous(at::MemoryFormat::ChannelsLast)).is_contiguous());
  }
}

TEST(ControlNetPipelineTest, RejectsControlItCannotUse) {
  const ControlledRun run = controlled_run();
  auto without = sdxl::SdxlPipeline::load(test::sdxl_model_dir(), sdxl::PipelineOptions{});
  ASSERT_TRUE(without.ok());
  EXPECT_EQ((*without)->controlnet(), nullptr);
  auto refused = (*without)->img2img(run.ref.at("image"), {"a"}, run.params, {1},
                                     sdxl::ControlInput{run.ref.at("control_image"), {1.0}});
  EXPECT_TRUE(contains_all(std::string(refused.status().message()), {"no ControlNet is loaded"}));

  sdxl::PipelineOptions options;
  options.controlnet = controlnet_dir();
  auto pipeline = sdxl::SdxlPipeline::load(test::sdxl_model_dir(), options);
  ASSERT_TRUE(pipeline.ok());
  const at::Tensor image = run.ref.at("image");
  EXPECT_FALSE(
      (*pipeline)->img2img(image, {"a"}, run.params, {1}, sdxl::ControlInput{image.slice(2, 0, 16), {1.0}}).ok());
  EXPECT_FALSE((*pipeline)->img2img(image, {"a"}, run.params, {1}, sdxl::ControlInput{image, {1.0, 1.0, 1.0}}).ok());
  EXPECT_FALSE(
      (*pipeline)->img2img(image, {"a"}, run.params, {1}, sdxl::ControlInput{image.slice(1, 0, 1), {1.0}}).ok());

  // A folder that is not a ControlNetModel is refused at load, naming the component.
  options.controlnet = test::sdxl_model_dir() + "/unet";
  auto wrong = sdxl::SdxlPipeline::load(test::sdxl_model_dir(), options);
  EXPECT_TRUE(contains_all(std::string(wrong.status().message()), {"controlnet", "not a ControlNetModel"}));
}

class ControlNetComponentTest : public test::TempDirTest {};

// A saved StableDiffusionXLControlNet*Pipeline lists its ControlNet in model_index.json: loaded without
// the controlnet option, and refused by name when it is not a ControlNetModel.
TEST_F(ControlNetComponentTest, LoadsTheControlNetComponentOfAPipelineFolder) {
  const auto model = dir_ / "model";
  std::filesystem::copy(test::sdxl_model_dir(), model, std::filesystem::copy_options::recursive);
  std::filesystem::copy(controlnet_dir(), model / "controlnet", std::filesystem::copy_options::recursive);
  std::ifstream index_in(test::sdxl_model_dir() + "/model_index.json");
  nlohmann::json index = nlohmann::json::parse(index_in);
  index["controlnet"] = {"diffusers", "ControlNetModel"};
  std::ofstream(model / "model_index.json") << index.dump();
  auto pipeline = sdxl::SdxlPipeline::load(model.string(), sdxl::PipelineOptions{});
  ASSERT_TRUE(pipeline.ok()) << pipeline.status();
  ASSERT_NE((*pipeline)->controlnet(), nullptr);
  const TensorMap ref = controlnet_reference("controlnet");
  expect_close((*pipeline)
                   ->controlnet()
                   ->forward(test::recorded_unet_inputs(ref), ref.at("controlnet_cond"), ref.at("conditioning_scale"))
                   .mid,
               ref.at("mid"), kTolerance, "mid residual of the folder's ControlNet");

  index["controlnet"] = {"diffusers", "ControlNetXSAdapter"};
  std::ofstream(model / "model_index.json") << index.dump();
  auto refused = sdxl::SdxlPipeline::load(model.string(), sdxl::PipelineOptions{});
  EXPECT_TRUE(contains_all(std::string(refused.status().message()), {"controlnet", "ControlNetXSAdapter"}));
}

class ControlNetLoadingTest : public ::testing::Test {
 protected:
  void SetUp() override {
    auto json = sdxl::read_json_file(controlnet_dir() + "/config.json");
    ASSERT_TRUE(json.ok());
    json_ = *json;
    auto config = sdxl::ControlNetConfig::from_json(json_);
    ASSERT_TRUE(config.ok()) << config.status();
    config_ = *config;
    auto weights = sdxl::read_folder_weights(controlnet_dir());
    ASSERT_TRUE(weights.ok());
    weights_ = *weights;
  }
  std::string load_error(const TensorMap& weights) const {
    auto net = sdxl::ControlNet::load(config_, weights, at::TensorOptions().dtype(at::kFloat), "cn");
    return net.ok() ? "" : std::string(net.status().message());
  }
  nlohmann::json json_;
  sdxl::ControlNetConfig config_;
  TensorMap weights_;
};

TEST_F(ControlNetLoadingTest, MissingMisshapedAndExtraTensorsAreNamed) {
  EXPECT_EQ(load_error(weights_), "");
  TensorMap missing = weights_;
  missing.erase("controlnet_down_blocks.3.weight");
  missing.erase("down_blocks.1.attentions.0.transformer_blocks.1.attn2.to_k.weight");
  EXPECT_TRUE(contains_all(load_error(missing), {"controlnet_down_blocks.3.weight [16, 16, 1, 1]",
                                                 "down_blocks.1.attentions.0.transformer_blocks.1.attn2.to_k.weight"}));
  TensorMap misshaped = weights_;
  misshaped["controlnet_mid_block.weight"] = at::zeros({32, 16, 1, 1});
  misshaped["controlnet_cond_embedding.conv_in.weight"] = at::zeros({8, 1, 3, 3});
  EXPECT_TRUE(
      contains_all(load_error(misshaped), {"controlnet_mid_block.weight (checkpoint [32, 16, 1, 1]",
                                           "controlnet_cond_embedding.conv_in.weight (checkpoint [8, 1, 3, 3]"}));
  TensorMap extra = weights_;
  extra["controlnet_down_blocks.6.weight"] = at::zeros({32, 32, 1, 1});
  EXPECT_TRUE(contains_all(load_error(extra), {"controlnet_down_blocks.6.weight"}));
}

TEST_F(ControlNetLoadingTest, UnsupportedConfigsAndMismatchedUNetsAreErrors) {
  nlohmann::json pooled = json_;
  pooled["global_pool_conditions"] = true;
  EXPECT_TRUE(contains_all(std::string(sdxl::ControlNetConfig::from_json(pooled).status().message()),
                           {"global_pool_conditions"}));
  nlohmann::json order = json_;
  order["controlnet_conditioning_channel_order"] = "gbr";
  EXPECT_FALSE(sdxl::ControlNetConfig::from_json(order).ok());

  auto net = sdxl::ControlNet::load(config_, weights_, at::TensorOptions().dtype(at::kFloat), "cn");
  ASSERT_TRUE(net.ok());
  auto folder = sdxl::ModelFolder::open(test::sdxl_model_dir());
  sdxl::UNetConfig unet = *sdxl::UNetConfig::from_json(*folder->read_json("unet"));
  EXPECT_TRUE(net->check_compatible(unet).ok());
  unet.block_out_channels = {16, 64};
  unet.cross_attention_dim = 32;
  EXPECT_TRUE(
      contains_all(std::string(net->check_compatible(unet).message()), {"block_out_channels", "cross_attention_dim"}));
}

// --- The depth conditioning image, by hand.

at::Tensor mask_row(std::vector<int64_t> values) {
  const auto n = static_cast<int64_t>(values.size());
  return at::tensor(values, at::kLong).to(at::kBool).view({1, n});
}

TEST(DepthControlTest, InverseDepthNormalisedOverCoveredPixels) {
  // Rendered depth is alpha-weighted: expected distances 1, 2, 4 and one pixel below tau_alpha = 0.5.
  const at::Tensor alpha = at::tensor({1.0f, 0.5f, 1.0f, 0.4f}).view({1, 4});
  const at::Tensor depth = at::tensor({1.0f, 1.0f, 4.0f, 0.4f}).view({1, 4});
  DepthControlOptions options;
  options.max_relative_variance = 1e9;  // the variance test is below
  auto control = depth_control_image(depth, alpha, options);
  ASSERT_TRUE(control.ok()) << control.status();
  ASSERT_EQ(control->image.sizes(), (at::IntArrayRef{3, 1, 4}));
  // 1/d = 1, 0.5, 0.25 -> (x - 0.25) / 0.75 = 1, 1/3, 0; the uncovered pixel is 0.
  const at::Tensor expected = at::tensor({1.0f, 1.0f / 3.0f, 0.0f, 0.0f}).view({1, 4});
  for (int c = 0; c < 3; ++c) EXPECT_TRUE(at::allclose(control->image[c], expected, 1e-6, 1e-7)) << control->image;
  EXPECT_TRUE(at::equal(control->reliable, mask_row({1, 1, 1, 0})));
  // A higher tau_alpha drops the half-covered pixel: 1/d = 1, 0.25 -> 1, 0.
  options.min_alpha = 0.6;
  control = depth_control_image(depth, alpha, options);
  ASSERT_TRUE(control.ok());
  EXPECT_TRUE(at::allclose(control->image[0], at::tensor({1.0f, 0.0f, 0.0f, 0.0f}).view({1, 4})));
}

TEST(DepthControlTest, HighLocalDepthVarianceIsMaskedOut) {
  // Distances 1, 1, 1, 3 in a row, 3 x 3 windows (rows beyond the image hold no covered pixel):
  //   pixel 0: {1, 1} -> Var/mean^2 = 0;  pixel 1: {1, 1, 1} -> 0;
  //   pixel 2: {1, 1, 3}: mean 5/3, mean of squares 11/3, Var = 8/9 -> 8/25 = 0.32;
  //   pixel 3: {1, 3}: mean 2, mean of squares 5, Var = 1 -> 1/4 = 0.25.
  const at::Tensor depth = at::tensor({1.0f, 1.0f, 1.0f, 3.0f}).view({1, 4});
  const at::Tensor alpha = at::ones({1, 4});
  DepthControlOptions options;
  options.max_relative_variance = 0.3;  // drops pixel 2 only; reliable 1/d = 1, 1, 1/3 -> 1, 1, 0
  auto control = depth_control_image(depth, alpha, options);
  ASSERT_TRUE(control.ok());
  EXPECT_TRUE(at::equal(control->reliable, mask_row({1, 1, 0, 1})));
  EXPECT_TRUE(at::allclose(control->image[1], at::tensor({1.0f, 1.0f, 0.0f, 0.0f}).view({1, 4})));
  options.max_relative_variance = 0.2;  // drops pixels 2 and 3; the rest has one depth -> 1
  control = depth_control_image(depth, alpha, options);
  ASSERT_TRUE(control.ok());
  EXPECT_TRUE(at::equal(control->reliable, mask_row({1, 1, 0, 0})));
  EXPECT_TRUE(at::allclose(control->image[2], at::tensor({1.0f, 1.0f, 0.0f, 0.0f}).view({1, 4})));
  // The default (0.01) keeps a smooth slope: distances 2.00, 2.02, 2.04, 2.06.
  control = depth_control_image(at::tensor({2.0f, 2.02f, 2.04f, 2.06f}).view({1, 4}), alpha);
  ASSERT_TRUE(control.ok());
  EXPECT_TRUE(control->reliable.all().item<bool>());
  EXPECT_FALSE(depth_control_image(depth, at::ones({2, 2})).ok());
  options.variance_window = 2;
  EXPECT_FALSE(depth_control_image(depth, alpha, options).ok());
}

// --- The sdxl backend with a ControlNet.

GenerationRequest depth_request(int64_t h, int64_t w, double scale, uint64_t seed) {
  GenerationRequest r;
  r.render_rgb = at::rand({h, w, 3});
  r.render_alpha = at::rand({h, w}) * 0.5 + 0.5;
  r.render_depth = (at::linspace(1.0, 3.0, h).view({h, 1}) + at::zeros({1, w})) * r.render_alpha;
  r.strength = 0.5;
  r.control_scale = scale;
  r.seed = seed;
  return r;
}

// Depth-Anything's disparity as a control image: min-max normalised, every pixel reliable; constant -> 1.
TEST(DepthControlTest, DisparityNormalisedToItsRange) {
  auto control = disparity_control_image(at::tensor({2.0f, 4.0f, 3.0f, 6.0f}).view({2, 2}));
  ASSERT_TRUE(control.ok()) << control.status();
  EXPECT_EQ(control->image.sizes(), (std::vector<int64_t>{3, 2, 2}));
  EXPECT_TRUE(at::allclose(control->image[2], at::tensor({0.0f, 0.5f, 0.25f, 1.0f}).view({2, 2})));
  EXPECT_TRUE(control->reliable.all().item<bool>());
  control = disparity_control_image(at::full({2, 3}, 7.0f));
  ASSERT_TRUE(control.ok());
  EXPECT_TRUE(at::equal(control->image, at::ones({3, 2, 3})));
  EXPECT_FALSE(disparity_control_image(at::ones({4})).ok());
  EXPECT_FALSE(disparity_control_image(at::tensor({1.0f, NAN}).view({1, 2})).ok());
}

TEST(SdxlControlNetGeneratorTest, ConditionsEachRequestOnItsDepth) {
  const std::string options = "{\"weights\": \"" + test::sdxl_model_dir() + "\", \"controlnet\": \"" +
                              controlnet_dir() + "\", \"steps\": 4, \"prompt\": \"a fern\"}";
  auto generator = make_generator("sdxl", options);
  ASSERT_TRUE(generator.ok()) << generator.status();
  // LoRA training (when a job asks for it) would take the views' control images from their rendered depth.
  EXPECT_EQ((*generator)->name(), "sdxl 1 controlnet lora-depth:rendered");
  std::vector<GenerationRequest> requests{depth_request(12, 8, 1.0, 1), depth_request(12, 8, 0.25, 2)};
  auto images = (*generator)->generate(requests);
  ASSERT_TRUE(images.ok()) << images.status();

  // The second request equals the pipeline's img2img with its depth image and scale.
  sdxl::PipelineOptions pipeline_options;
  pipeline_options.controlnet = controlnet_dir();
  auto pipeline = sdxl::SdxlPipeline::load(test::sdxl_model_dir(), pipeline_options);
  ASSERT_TRUE(pipeline.ok());
  auto control = depth_control_image(requests[1].render_depth, requests[1].render_alpha);
  ASSERT_TRUE(control.ok());
  sdxl::Img2ImgParams params;
  params.steps = 4;
  params.strength = 0.5;
  auto direct = (*pipeline)->img2img(requests[1].render_rgb.permute({2, 0, 1}).unsqueeze(0), {"a fern"}, params, {2},
                                     sdxl::ControlInput{control->image.unsqueeze(0), {0.25}});
  ASSERT_TRUE(direct.ok()) << direct.status();
  expect_close((*images)[1], (*direct)[0].permute({1, 2, 0}), 1e-5, "generator vs pipeline with ControlNet");
  // Scale 0 is the unconditioned backend's image.
  auto plain =
      make_generator("sdxl", "{\"weights\": \"" + test::sdxl_model_dir() + "\", \"steps\": 4, \"prompt\": \"a fern\"}");
  ASSERT_TRUE(plain.ok());
  requests[1].control_scale = 0.0;
  auto zero = (*generator)->generate({requests[1]});
  auto unconditioned = (*plain)->generate({requests[1]});
  ASSERT_TRUE(zero.ok() && unconditioned.ok());
  expect_close((*zero)[0], (*unconditioned)[0], 1e-6, "scale 0 vs no ControlNet");
  EXPECT_GT(((*zero)[0] - (*images)[1]).abs().max().item<double>(), 1e-4);

  // A request without depth cannot be conditioned.
  requests[0].render_depth = at::Tensor();
  EXPECT_TRUE(contains_all(std::string((*generator)->generate({requests[0]}).status().message()), {"render_depth"}));
  EXPECT_TRUE(contains_all(
      std::string(make_generator("sdxl", "{\"weights\": \"x\", \"control_variance_window\": 4}").status().message()),
      {"control_variance_window"}));
}

}  // namespace
}  // namespace gaps

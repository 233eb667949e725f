// The diffusion pipelines on CUDA in half precision, against the float32 references their CPU parity
// suites check (sdxl_pipeline_test.cpp, sdxl_controlnet_test.cpp, sdxl_ip_adapter_test.cpp,
// sd2_inpaint_test.cpp), and CUDA-graph replay (of img2img's UNet, of LoRA training's step) against eager runs,
// also on a second GPU while the first is current. Half precision follows the float32 result on the tiny random
// weights within its rounding: 5e-2 for float16 (11-bit mantissa), 1e-1 for bfloat16 (8-bit).
#include <algorithm>
#include <cmath>
#include <map>
#include <memory>
#include <string>
#include <utility>
#include <vector>

#include <ATen/ATen.h>
#include <ATen/cuda/CUDAContext.h>
#include <c10/cuda/CUDAGuard.h>
#include <gtest/gtest.h>
#include <nlohmann/json.hpp>
#include "absl/strings/str_cat.h"

#include "diffusion_worker/backend_registry.h"
#include "diffusion_worker/sdxl/inpaint_pipeline.h"
#include "diffusion_worker/sdxl/pipeline.h"
#include "tests/controlnet_test_util.h"
#include "tests/gpu/require_cuda.h"
#include "tests/ip_adapter_test_util.h"
#include "tests/sd2_inpaint_test_util.h"
#include "tests/sdxl_test_util.h"

namespace gaps::sdxl {
namespace {

using test::expect_close;

// The tiny SDXL with its tiny ControlNet, float16 on a GPU (the current one unless given).
absl::StatusOr<std::unique_ptr<SdxlPipeline>> half_precision_controlnet_pipeline(
    at::Device device = at::Device(at::kCUDA), bool channels_last = false) {
  PipelineOptions options{at::kHalf, device, ""};
  options.controlnet = test::controlnet_dir();
  options.channels_last = channels_last;
  return SdxlPipeline::load(test::sdxl_model_dir(), options);
}

// Turns the pipeline's UNet graphs on and runs the controlled img2img twice (capture, then replay): each within
// 1e-3 of the eager result.
void expect_graphs_give(SdxlPipeline& pipeline, const test::ControlledRun& run, const ControlInput& control,
                        const at::Tensor& eager, const std::string& what) {
  ASSERT_TRUE(pipeline.set_cuda_graphs(true).ok());
  const auto prompts = run.setup["prompts"].get<std::vector<std::string>>();
  for (int pass = 0; pass < 2; ++pass) {
    auto graphed = pipeline.img2img(run.ref.at("image"), prompts, run.params, {1234}, control);
    ASSERT_TRUE(graphed.ok()) << graphed.status();
    expect_close(*graphed, eager, 1e-3, what);
  }
}

// The losses of 5 LoRA training steps on the controlled run's images (learning rate 1e-3, seed 11).
std::vector<double> five_lora_losses(SdxlPipeline& pipeline, const test::ControlledRun& run, bool cuda_graph) {
  LoraTrainingOptions training;
  training.steps = 5;
  training.learning_rate = 1e-3;
  training.seed = 11;
  training.cuda_graph = cuda_graph;
  auto trained = pipeline.train_lora(run.ref.at("image"), {"a photo of a fern"},
                                     ControlInput{run.ref.at("control_image"), {1.0}}, LoraConfig{}, training);
  EXPECT_TRUE(trained.ok()) << trained.status();
  EXPECT_EQ(trained.ok() ? trained->size() : 0u, 5u);
  return trained.ok() ? *trained : std::vector<double>(5, 0.0);
}

TEST(SdxlPipelineTest, LoadsOnTheGpuInHalfPrecision) {
  GAPS_REQUIRE_CUDA();
  for (const auto& [dtype, tolerance] : {std::pair{at::kHalf, 5e-2}, std::pair{at::kBFloat16, 1e-1}}) {
    auto pipeline = SdxlPipeline::load(test::sdxl_model_dir(), PipelineOptions{dtype, at::Device(at::kCUDA), ""});
    ASSERT_TRUE(pipeline.ok()) << pipeline.status();
    const TensorMap ref = test::sdxl_reference("img2img");
    Img2ImgParams params;
    params.steps = 4;
    auto out =
        (*pipeline)->img2img(ref.at("image"), {"a photo of a fern in a garden", "a bonsai tree"}, params, {1234});
    ASSERT_TRUE(out.ok()) << out.status();
    expect_close(*out, ref.at("out"), tolerance, "half-precision img2img output");
    // Replaying captured UNet graphs gives the eager result.
    ASSERT_TRUE((*pipeline)->set_cuda_graphs(true).ok());
    for (int run = 0; run < 2; ++run) {  // capture, then replay the captured graph
      auto graphed =
          (*pipeline)->img2img(ref.at("image"), {"a photo of a fern in a garden", "a bonsai tree"}, params, {1234});
      ASSERT_TRUE(graphed.ok()) << graphed.status();
      expect_close(*graphed, *out, 1e-3, "img2img with CUDA graphs");
    }
  }
}

// The VAE in a half type on request (vae_dtype), although the tiny VAE's config asks for force_upcast as SDXL's
// does: it runs in that type and img2img still follows the float32 reference within that type's rounding.
TEST(SdxlPipelineTest, RunsItsVaeInTheTypeAskedFor) {
  GAPS_REQUIRE_CUDA();
  const TensorMap ref = test::sdxl_reference("img2img");
  Img2ImgParams params;
  params.steps = 4;
  for (const auto& [vae_dtype, tolerance] : {std::pair{at::kBFloat16, 1e-1}, std::pair{at::kHalf, 5e-2}}) {
    PipelineOptions options{at::kHalf, at::Device(at::kCUDA), ""};
    options.vae_dtype = vae_dtype;
    auto pipeline = SdxlPipeline::load(test::sdxl_model_dir(), options);
    ASSERT_TRUE(pipeline.ok()) << pipeline.status();
    EXPECT_EQ((*pipeline)->vae().dtype(), vae_dtype);
    auto out =
        (*pipeline)->img2img(ref.at("image"), {"a photo of a fern in a garden", "a bonsai tree"}, params, {1234});
    ASSERT_TRUE(out.ok()) << out.status();
    expect_close(*out, ref.at("out"), tolerance, "img2img with a half-precision VAE");
  }
  auto upcast = SdxlPipeline::load(test::sdxl_model_dir(), PipelineOptions{at::kHalf, at::Device(at::kCUDA), ""});
  ASSERT_TRUE(upcast.ok()) << upcast.status();
  EXPECT_EQ((*upcast)->vae().dtype(), at::kFloat) << "force_upcast keeps the VAE in float32 when none is asked for";
}

TEST(ControlNetPipelineTest, RunsOnTheGpuInHalfPrecisionAndFromCudaGraphs) {
  GAPS_REQUIRE_CUDA();
  auto pipeline = half_precision_controlnet_pipeline();
  ASSERT_TRUE(pipeline.ok()) << pipeline.status();
  const test::ControlledRun run = test::controlled_run();
  const auto prompts = run.setup["prompts"].get<std::vector<std::string>>();
  const ControlInput control{run.ref.at("control_image"), {run.setup["controlnet_conditioning_scale"].get<double>()}};
  auto out = (*pipeline)->img2img(run.ref.at("image"), prompts, run.params, {1234}, control);
  ASSERT_TRUE(out.ok()) << out.status();
  expect_close(*out, run.ref.at("out"), 5e-2, "half-precision ControlNet img2img");
  // The residuals are inputs of the captured UNet graph: replay gives the eager result, and a run
  // without control (another graph) is not affected by the controlled one.
  auto plain = (*pipeline)->img2img(run.ref.at("image"), prompts, run.params, {1234});
  ASSERT_TRUE(plain.ok());
  ASSERT_TRUE((*pipeline)->set_cuda_graphs(true).ok());
  for (int pass = 0; pass < 2; ++pass) {  // capture, then replay
    auto graphed = (*pipeline)->img2img(run.ref.at("image"), prompts, run.params, {1234}, control);
    ASSERT_TRUE(graphed.ok()) << graphed.status();
    expect_close(*graphed, *out, 1e-3, "ControlNet img2img with CUDA graphs");
    auto graphed_plain = (*pipeline)->img2img(run.ref.at("image"), prompts, run.params, {1234});
    ASSERT_TRUE(graphed_plain.ok());
    expect_close(*graphed_plain, *plain, 1e-3, "img2img without control with CUDA graphs");
  }
}

TEST(IpAdapterPipelineTest, RunsOnTheGpuInHalfPrecisionAndReplaysCudaGraphsWithNewPrompts) {
  GAPS_REQUIRE_CUDA();
  PipelineOptions options = test::ip_options();
  options.dtype = at::kHalf;
  options.device = at::Device(at::kCUDA);
  auto pipeline = SdxlPipeline::load(test::sdxl_model_dir(), options);
  ASSERT_TRUE(pipeline.ok()) << pipeline.status();
  const TensorMap ref = test::ip_reference("img2img");
  const TensorMap images = test::ip_reference("encoder");
  const std::vector<std::string> prompts{"a photo of a fern in a garden", "a bonsai tree"};
  Img2ImgParams params;
  params.steps = 4;
  params.reference_images = {images.at("image_0"), images.at("image_0")};
  auto eager = (*pipeline)->img2img(ref.at("image"), prompts, params, {1234});
  ASSERT_TRUE(eager.ok()) << eager.status();
  expect_close(*eager, ref.at("out"), 5e-2, "half-precision img2img with IP-Adapter");
  params.reference_images = {images.at("image_1"), at::Tensor()};
  auto eager_other = (*pipeline)->img2img(ref.at("image"), prompts, params, {1234});
  ASSERT_TRUE(eager_other.ok()) << eager_other.status();
  // Captured graphs read the image prompt's buffers: a replay with other references gives their result.
  ASSERT_TRUE((*pipeline)->set_cuda_graphs(true).ok());
  for (int run = 0; run < 2; ++run) {
    params.reference_images = {images.at("image_0"), images.at("image_0")};
    auto graphed = (*pipeline)->img2img(ref.at("image"), prompts, params, {1234});
    ASSERT_TRUE(graphed.ok()) << graphed.status();
    expect_close(*graphed, *eager, 1e-3, "graphed img2img with IP-Adapter");
    params.reference_images = {images.at("image_1"), at::Tensor()};
    auto graphed_other = (*pipeline)->img2img(ref.at("image"), prompts, params, {1234});
    ASSERT_TRUE(graphed_other.ok()) << graphed_other.status();
    expect_close(*graphed_other, *eager_other, 1e-3, "graphed img2img with other references");
  }
}

TEST(Sd2InpaintPipelineTest, RunsOnTheGpuInHalfPrecision) {
  GAPS_REQUIRE_CUDA();
  const nlohmann::json& setup = test::sd2_inpaint_setup();
  for (const auto& [dtype, tolerance] : {std::pair{at::kHalf, 5e-2}, std::pair{at::kBFloat16, 1e-1}}) {
    auto pipeline =
        InpaintPipeline::load(test::sd2_model_dir(), InpaintPipelineOptions{dtype, at::Device(at::kCUDA), ""});
    ASSERT_TRUE(pipeline.ok()) << pipeline.status();
    const TensorMap ref = test::sd2_reference("inpaint_ddim");
    InpaintParams params;
    params.steps = 2;
    params.guidance_scale = setup["guidance_scale"].get<double>();
    auto out = (*pipeline)->inpaint(ref.at("image"), ref.at("mask"), test::sd2_prompts(), params,
                                    {setup["seed"].get<uint64_t>()});
    ASSERT_TRUE(out.ok()) << out.status();
    expect_close(*out, ref.at("out"), tolerance, "half-precision inpainting");
  }
}

// LoRA training replayed from a captured CUDA graph takes the eager steps' draws and updates: the same loss at
// Convolutions and activations in channels-last order (the GroupNorms through the fused kernel): the same images
// as the NCHW pipeline within half precision's rounding, from graphs as eagerly, and LoRA training (ATen's
// GroupNorm under autograd) with the NCHW pipeline's losses.
TEST(ControlNetPipelineTest, RunsChannelsLastAsItRunsNchw) {
  GAPS_REQUIRE_CUDA();
  auto nchw = half_precision_controlnet_pipeline();
  ASSERT_TRUE(nchw.ok()) << nchw.status();
  auto pipeline = half_precision_controlnet_pipeline(at::Device(at::kCUDA), /*channels_last=*/true);
  ASSERT_TRUE(pipeline.ok()) << pipeline.status();
  const test::ControlledRun run = test::controlled_run();
  const auto prompts = run.setup["prompts"].get<std::vector<std::string>>();
  const ControlInput control{run.ref.at("control_image"), {run.setup["controlnet_conditioning_scale"].get<double>()}};
  // The activations take the model's layout, whatever the input's.
  const at::Tensor images = (run.ref.at("image") * 2 - 1).to(at::kCUDA, (*pipeline)->vae().dtype());
  for (const at::Tensor& input : {images, images.contiguous(at::MemoryFormat::ChannelsLast)}) {
    const at::Tensor moments = (*pipeline)->vae().encode_moments(input);
    EXPECT_TRUE(moments.is_contiguous(at::MemoryFormat::ChannelsLast) && !moments.is_contiguous());
    EXPECT_TRUE((*nchw)->vae().encode_moments(input).is_contiguous());
  }
  auto expected = (*nchw)->img2img(run.ref.at("image"), prompts, run.params, {1234}, control);
  auto out = (*pipeline)->img2img(run.ref.at("image"), prompts, run.params, {1234}, control);
  ASSERT_TRUE(expected.ok() && out.ok()) << out.status();
  expect_close(*out, run.ref.at("out"), 5e-2, "channels-last half-precision ControlNet img2img");
  expect_close(*out, *expected, 2e-2, "channels-last against NCHW img2img");
  ASSERT_NO_FATAL_FAILURE(expect_graphs_give(**pipeline, run, control, *out, "channels-last img2img with CUDA graphs"));
  const std::vector<double> nchw_losses = five_lora_losses(**nchw, run, false);
  const std::vector<double> losses = five_lora_losses(**pipeline, run, false);
  for (size_t i = 0; i < losses.size(); ++i)
    EXPECT_NEAR(losses[i], nchw_losses[i], 1e-2 * std::abs(nchw_losses[i])) << "LoRA step " << i;
}

// every step (a replay that read stale noise or timesteps, or stale adapters, would differ at once) and the same
// trained adapters. Half precision: the two runs' kernels are the same, the attention's backward need not be
// deterministic.
TEST(LoraTrainingTest, ACudaGraphTrainsAsTheEagerStepsDo) {
  GAPS_REQUIRE_CUDA();
  auto pipeline = half_precision_controlnet_pipeline();
  ASSERT_TRUE(pipeline.ok()) << pipeline.status();
  const test::ControlledRun run = test::controlled_run();
  const ControlInput control{run.ref.at("control_image"), {1.0}};
  const at::Tensor images = run.ref.at("image");
  LoraConfig config;
  LoraTrainingOptions training;
  training.steps = 7;
  training.learning_rate = 1e-3;
  training.seed = 11;
  std::vector<std::vector<double>> losses;
  std::vector<std::vector<at::Tensor>> adapters;
  for (const bool cuda_graph : {false, true}) {
    training.cuda_graph = cuda_graph;
    auto trained = (*pipeline)->train_lora(images, {"a photo of a fern"}, control, config, training);
    ASSERT_TRUE(trained.ok()) << trained.status();
    ASSERT_EQ(trained->size(), 7u);
    losses.push_back(*trained);
    std::vector<at::Tensor> parameters;
    for (const at::Tensor& p : (*pipeline)->lora()->parameters()) parameters.push_back(p.detach().cpu().clone());
    adapters.push_back(std::move(parameters));
  }
  for (size_t i = 0; i < losses[0].size(); ++i) {
    EXPECT_NEAR(losses[1][i], losses[0][i], 1e-3 * std::abs(losses[0][i])) << "step " << i;
  }
  // The up matrices start at zero, so they are what training moved; a sign the nondeterministic backward
  // flips in a near-zero gradient moves one entry by 2 lr, hence a mean rather than a maximum.
  ASSERT_EQ(adapters[0].size(), adapters[1].size());
  double moved = 0, diff = 0;
  for (size_t i = 1; i < adapters[0].size(); i += 2) {
    moved += adapters[0][i].abs().sum().item<double>();
    diff += (adapters[1][i] - adapters[0][i]).abs().sum().item<double>();
  }
  EXPECT_GT(moved, 0.0);
  EXPECT_LE(diff, 0.02 * moved) << "summed |up| " << moved;
  RecordProperty("relative_up_diff", absl::StrCat(diff / moved));
}

// A pipeline on a second GPU while the first is the current device, as a worker placed on `cuda:1` in a process
// whose other work (the trainer) runs on `cuda:0`: the UNet's graphs and the LoRA training's graph must be captured
// on the pipeline's device. Captured on the current device instead, they are empty and a replay returns the first
// step's output at every step, which the comparisons with the eager runs catch.
TEST(SdxlPipelineTest, CapturesAndReplaysItsGraphsOnItsOwnDeviceWhenAnotherIsCurrent) {
  GAPS_REQUIRE_CUDA();
  if (at::cuda::device_count() < 2) GTEST_SKIP() << "needs two CUDA devices";
  const c10::cuda::CUDAGuard first_is_current(c10::DeviceIndex{0});
  auto pipeline = half_precision_controlnet_pipeline(at::Device(at::kCUDA, 1));
  ASSERT_TRUE(pipeline.ok()) << pipeline.status();
  const test::ControlledRun run = test::controlled_run();
  const auto prompts = run.setup["prompts"].get<std::vector<std::string>>();
  const ControlInput control{run.ref.at("control_image"), {run.setup["controlnet_conditioning_scale"].get<double>()}};
  auto eager = (*pipeline)->img2img(run.ref.at("image"), prompts, run.params, {1234}, control);
  ASSERT_TRUE(eager.ok()) << eager.status();
  expect_close(*eager, run.ref.at("out"), 5e-2, "ControlNet img2img on the second GPU");
  ASSERT_NO_FATAL_FAILURE(
      expect_graphs_give(**pipeline, run, control, *eager, "ControlNet img2img with CUDA graphs on the second GPU"));
  const std::vector<double> eager_losses = five_lora_losses(**pipeline, run, false);
  const std::vector<double> graphed_losses = five_lora_losses(**pipeline, run, true);
  for (size_t i = 0; i < eager_losses.size(); ++i)
    EXPECT_NEAR(graphed_losses[i], eager_losses[i], 1e-3 * std::abs(eager_losses[i])) << "LoRA step " << i;
  EXPECT_EQ(c10::cuda::current_device(), 0) << "the pipeline left another device current";
}

// The sdxl backend on a GPU merges requests of unequal strengths into one batch (a step's fixed cost is worth
// sharing there) and each image still comes out as it does alone: float16, ControlNet, UNet replayed from graphs.
// Steps of 4: 4, 3, 3, 2 cost 4 x (1 + 4) = 20 member-steps in one batch against 21 apart.
TEST(SdxlGeneratorCudaTest, MergesUnequalStrengthsIntoOneBatchAndEachImageComesOutAsAlone) {
  GAPS_REQUIRE_CUDA();
  const nlohmann::json options = {{"weights", test::sdxl_model_dir()},
                                  {"controlnet", test::controlnet_dir()},
                                  {"device", "cuda"},
                                  {"dtype", "float16"},
                                  {"cuda_graphs", true},
                                  {"steps", 4},
                                  {"batch_size", 4},
                                  {"prompt", "a fern"}};
  auto generator = make_generator("sdxl", options.dump());
  ASSERT_TRUE(generator.ok()) << generator.status();
  std::vector<GenerationRequest> requests;
  at::manual_seed(5);
  for (const double strength : {1.0, 0.75, 0.75, 0.5}) {
    GenerationRequest r;
    r.render_rgb = at::rand({12, 8, 3});
    r.render_depth = at::rand({12, 8}) + 1;
    r.render_alpha = at::ones({12, 8});
    r.strength = strength;
    r.seed = requests.size() + 1;
    requests.push_back(r);
  }
  auto images = (*generator)->generate(requests);
  ASSERT_TRUE(images.ok()) << images.status();
  const std::map<std::string, double> counters = (*generator)->counters();
  EXPECT_EQ(counters.at("img2img_batches"), 1.0);
  EXPECT_EQ(counters.at("img2img_member_steps"), 12.0);
  EXPECT_EQ(counters.at("img2img_batch_steps"), 16.0);
  for (size_t i = 0; i < requests.size(); ++i) {
    auto alone = (*generator)->generate({requests[i]});
    ASSERT_TRUE(alone.ok()) << alone.status();
    expect_close((*images)[i], (*alone)[0], 1e-2, absl::StrCat("request ", i, " in the merged batch vs alone"));
  }
}

}  // namespace
}  // namespace gaps::sdxl

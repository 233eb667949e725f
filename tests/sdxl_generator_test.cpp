// The `sdxl` backend through the registry: options, start-up errors for unusable folders, and
// generation on the tiny fixture model (padding to the latent factor, per-request strength and seed).
#include <filesystem>
#include <fstream>
#include <map>
#include <string>
#include <vector>

#include <ATen/ATen.h>
#include <gtest/gtest.h>
#include <nlohmann/json.hpp>
#include "absl/strings/str_cat.h"

#include "diffusion_worker/backend_registry.h"
#include "diffusion_worker/sdxl/pipeline.h"
#include "diffusion_worker/sdxl_generator.h"
#include "tests/sdxl_test_util.h"
#include "tests/test_util.h"

namespace gaps {
namespace {

using test::contains_all;

std::string options_json(const std::string& folder, const std::string& extra = "") {
  return "{\"weights\": \"" + folder + "\", \"steps\": 4, \"guidance\": 5.0, \"prompt\": \"a fern\"" + extra + "}";
}

GenerationRequest request(int64_t h, int64_t w, double strength, uint64_t seed) {
  GenerationRequest r;
  r.render_rgb = at::rand({h, w, 3});
  r.render_depth = at::ones({h, w});
  r.render_alpha = at::ones({h, w});
  r.strength = strength;
  r.seed = seed;
  return r;
}

TEST(SdxlGeneratorTest, RegisteredAndGeneratesAtEachRequestsStrength) {
  auto generator = make_generator("sdxl", options_json(test::sdxl_model_dir()));
  ASSERT_TRUE(generator.ok()) << generator.status();
  EXPECT_EQ((*generator)->name(), "sdxl 1");
  // 13 x 10 is padded to 14 x 10 (the tiny VAE's factor is 2) and cropped back.
  std::vector<GenerationRequest> requests{request(13, 10, 0.5, 1), request(13, 10, 0.5, 2), request(12, 8, 1.0, 3),
                                          request(12, 8, 0.1, 4)};
  auto images = (*generator)->generate(requests);
  ASSERT_TRUE(images.ok()) << images.status();
  ASSERT_EQ(images->size(), 4u);
  for (size_t i = 0; i < 3; ++i) {
    EXPECT_EQ((*images)[i].sizes(), requests[i].render_rgb.sizes());
    EXPECT_GE((*images)[i].min().item<float>(), 0.0f);
    EXPECT_LE((*images)[i].max().item<float>(), 1.0f);
    EXPECT_GT(((*images)[i] - requests[i].render_rgb).abs().max().item<double>(), 1e-3) << i;
  }
  // Strength 0.1 of 4 steps is less than one step: the render comes back unchanged.
  EXPECT_TRUE(at::equal((*images)[3], requests[3].render_rgb));

  // The same request alone gives the same image as in the batch (per-request seeds).
  auto alone = (*generator)->generate({requests[1]});
  ASSERT_TRUE(alone.ok());
  test::expect_close((*alone)[0], (*images)[1], 1e-4, "batched vs single generation");

  // And equals the pipeline's img2img on the padded render.
  auto pipeline = sdxl::SdxlPipeline::load(test::sdxl_model_dir(), sdxl::PipelineOptions{});
  ASSERT_TRUE(pipeline.ok());
  const at::Tensor padded = at::replication_pad2d(requests[1].render_rgb.permute({2, 0, 1}).unsqueeze(0), {0, 0, 0, 1});
  sdxl::Img2ImgParams params;
  params.steps = 4;
  params.strength = 0.5;
  auto direct = (*pipeline)->img2img(padded, {"a fern"}, params, {2});
  ASSERT_TRUE(direct.ok());
  test::expect_close((*alone)[0], (*direct)[0].slice(1, 0, 13).permute({1, 2, 0}), 1e-5, "generator vs pipeline");
}

// channels_last: the models convolve channels-last (the VAE's moments come out so) and the images are NCHW's.
TEST(SdxlGeneratorTest, ChannelsLastGivesTheImagesOfNchw) {
  SdxlOptions options;
  options.weights = test::sdxl_model_dir();
  options.steps = 4;
  options.prompt = "a fern";
  auto nchw = SdxlGenerator::create(options);
  options.channels_last = true;
  auto channels_last = SdxlGenerator::create(options);
  ASSERT_TRUE(nchw.ok() && channels_last.ok()) << channels_last.status();
  const at::Tensor images = at::rand({1, 3, 16, 12}) * 2 - 1;
  EXPECT_TRUE((*channels_last)->pipeline().vae().encode_moments(images).is_contiguous(at::MemoryFormat::ChannelsLast));
  EXPECT_TRUE((*nchw)->pipeline().vae().encode_moments(images).is_contiguous());
  const std::vector<GenerationRequest> requests{request(13, 10, 0.5, 1), request(12, 8, 1.0, 3)};
  auto expected = (*nchw)->generate(requests);
  auto out = (*channels_last)->generate(requests);
  ASSERT_TRUE(expected.ok() && out.ok()) << out.status();
  for (size_t i = 0; i < requests.size(); ++i)
    test::expect_close((*out)[i], (*expected)[i], 1e-4, "channels-last against NCHW generation");
}

// The batching of requests by their denoising steps (sorted, most first).
TEST(SdxlBatchingTest, MergesUnequalStepsOnlyWhenABatchStepsFixedCostIsWorthIt) {
  EXPECT_TRUE(img2img_batch_ends({}, 8, 1.0).empty());
  // Without a fixed cost only equal steps share a batch.
  EXPECT_EQ(img2img_batch_ends({10, 10, 10, 9, 9}, 8, 0.0), (std::vector<size_t>{3, 5}));
  // With one: 11 x (1 + 4) = 55 member-steps together, against 11 x 2 + 10 x 3 + 9 x 2 = 70 apart.
  EXPECT_EQ(img2img_batch_ends({11, 10, 10, 9}, 8, 1.0), (std::vector<size_t>{4}));
  // A long request alone, not dragging seven short ones through its steps: 25 x 2 + 10 x 8 against 25 x 9.
  EXPECT_EQ(img2img_batch_ends({25, 10, 10, 10, 10, 10, 10, 10}, 8, 1.0), (std::vector<size_t>{1, 8}));
  // The batch size caps a batch.
  for (const std::vector<size_t>& ends :
       {img2img_batch_ends({5, 5, 5, 5, 5}, 2, 1.0), img2img_batch_ends({5, 5, 5, 5, 5}, 2, 0.0)}) {
    ASSERT_EQ(ends.size(), 3u);
    EXPECT_EQ(ends.back(), 5u);
    for (size_t b = 0, begin = 0; b < ends.size(); begin = ends[b++]) EXPECT_LE(ends[b] - begin, 2u);
  }
}

// The counters of a generate() call: batches, the steps asked for and the steps computed. On the CPU (no fixed
// cost per step) requests of unequal steps run in batches of their own.
TEST(SdxlGeneratorTest, CountsItsBatchesAndSteps) {
  auto generator = make_generator("sdxl", options_json(test::sdxl_model_dir(), ", \"batch_size\": 4"));
  ASSERT_TRUE(generator.ok()) << generator.status();
  // Steps of 4: 4, 2, 3, 2 and (strength 0.1) none.
  std::vector<GenerationRequest> requests{request(12, 8, 1.0, 1), request(12, 8, 0.5, 2), request(12, 8, 0.75, 3),
                                          request(12, 8, 0.5, 4), request(12, 8, 0.1, 5)};
  auto images = (*generator)->generate(requests);
  ASSERT_TRUE(images.ok()) << images.status();
  const std::map<std::string, double> counters = (*generator)->counters();
  EXPECT_EQ(counters.at("img2img_batches"), 3.0);
  EXPECT_EQ(counters.at("img2img_member_steps"), 11.0);
  EXPECT_EQ(counters.at("img2img_batch_steps"), 11.0);
  auto alone = (*generator)->generate({requests[2]});
  ASSERT_TRUE(alone.ok());
  test::expect_close((*alone)[0], (*images)[2], 1e-4, "batched vs single generation");
  EXPECT_EQ((*generator)->counters().at("img2img_member_steps"), 3.0);  // of the last call only

  // With a fixed cost of 3 per step the four share one batch: 4 x (3 + 4) = 28 member-steps, against 30 for the next
  // best cut ({4, 3} and {2, 2}) and 38 apart;
  // and each image comes out as it did in its own batch.
  auto merging =
      make_generator("sdxl", options_json(test::sdxl_model_dir(), ", \"batch_size\": 4, \"batch_step_overhead\": 3"));
  ASSERT_TRUE(merging.ok()) << merging.status();
  auto merged = (*merging)->generate(requests);
  ASSERT_TRUE(merged.ok()) << merged.status();
  EXPECT_EQ((*merging)->counters().at("img2img_batches"), 1.0);
  EXPECT_EQ((*merging)->counters().at("img2img_member_steps"), 11.0);
  EXPECT_EQ((*merging)->counters().at("img2img_batch_steps"), 16.0);
  for (size_t i = 0; i < requests.size(); ++i)
    test::expect_close((*merged)[i], (*images)[i], 1e-4, absl::StrCat("request ", i, " merged vs apart"));
  EXPECT_FALSE(make_generator("sdxl", options_json(test::sdxl_model_dir(), ", \"batch_step_overhead\": -1")).ok());
}

// Without an IP-Adapter loaded, requests that ask for an image prompt are generated without one and the
// generator says so; a scale of 0 asks for none.
TEST(SdxlGeneratorTest, AnImagePromptWithoutAnIpAdapterIsNoted) {
  auto generator = make_generator("sdxl", options_json(test::sdxl_model_dir()));
  ASSERT_TRUE(generator.ok()) << generator.status();
  GenerationRequest asking = request(12, 8, 0.5, 1);
  ReferenceView nearest;
  nearest.image = at::rand({12, 8, 3});
  asking.references = {nearest};
  GenerationRequest plain = asking;
  plain.ip_adapter_scale = 0.0;
  asking.ip_adapter_scale = 0.5;
  auto images = (*generator)->generate({asking, plain});
  ASSERT_TRUE(images.ok()) << images.status();
  EXPECT_TRUE(at::equal((*images)[0], (*images)[1]));
  EXPECT_EQ((*generator)->notes(),
            std::vector<std::string>{"sdxl has no IP-Adapter loaded (options ip_adapter, image_encoder): 1/2 requests "
                                     "asked for ip_adapter_scale 0.5, generated without an image prompt"});
  ASSERT_TRUE((*generator)->generate({plain}).ok());
  EXPECT_TRUE((*generator)->notes().empty());
}

class SdxlGeneratorStartupTest : public test::TempDirTest {};

TEST_F(SdxlGeneratorStartupTest, UnusableFoldersAreClearErrors) {
  EXPECT_TRUE(contains_all(std::string(make_generator("sdxl", "").status().message()), {"weights"}));
  EXPECT_TRUE(contains_all(std::string(make_generator("sdxl", R"({"weights": "x", "stepz": 3})").status().message()),
                           {"unknown sdxl option 'stepz'"}));
  EXPECT_TRUE(contains_all(
      std::string(
          make_generator("sdxl", options_json(test::sdxl_model_dir(), ", \"dtype\": \"int8\"")).status().message()),
      {"dtype"}));
  EXPECT_TRUE(contains_all(
      std::string(
          make_generator("sdxl", options_json(test::sdxl_model_dir(), ", \"dtype\": \"float16\"")).status().message()),
      {"float32"}));

  EXPECT_TRUE(contains_all(
      std::string(make_generator("sdxl", options_json(test::sdxl_model_dir(), ", \"vae_dtype\": \"bfloat16\""))
                      .status()
                      .message()),
      {"vae_dtype", "float32"}));
  EXPECT_TRUE(contains_all(
      std::string(
          make_generator("sdxl", options_json(test::sdxl_model_dir(), ", \"vae_dtype\": \"int8\"")).status().message()),
      {"vae_dtype"}));
  EXPECT_TRUE(make_generator("sdxl", options_json(test::sdxl_model_dir(), ", \"vae_dtype\": \"float32\"")).ok());

  EXPECT_TRUE(contains_all(
      std::string(
          make_generator("sdxl", options_json(test::sdxl_model_dir(), ", \"cuda_graphs\": true")).status().message()),
      {"CUDA"}));

  EXPECT_TRUE(contains_all(
      std::string(
          make_generator("sdxl", options_json(test::sdxl_model_dir(), ", \"variant\": \"fp16\"")).status().message()),
      {"no fp16 *.safetensors weights"}));

  const auto missing = make_generator("sdxl", options_json((dir_ / "absent").string()));
  EXPECT_TRUE(contains_all(std::string(missing.status().message()), {"not a usable SDXL model", "does not exist"}));

  write("model/model_index.json",
        R"({"_class_name": "StableDiffusionPipeline", "unet": ["diffusers", "UNet2DConditionModel"]})");
  const auto partial = make_generator("sdxl", options_json((dir_ / "model").string()));
  EXPECT_TRUE(
      contains_all(std::string(partial.status().message()), {"not a usable SDXL model", "lists no component 'vae'"}));

  // A copy of the tiny model whose UNet weights lost a tensor.
  for (const auto& entry : std::filesystem::recursive_directory_iterator(test::sdxl_model_dir())) {
    const auto relative = std::filesystem::relative(entry.path(), test::sdxl_model_dir());
    if (entry.is_directory()) {
      std::filesystem::create_directories(dir_ / "copy" / relative);
    } else if (relative.filename() != "diffusion_pytorch_model.safetensors" || relative.parent_path() != "unet") {
      std::filesystem::copy_file(entry.path(), dir_ / "copy" / relative);
    }
  }
  auto unet = sdxl::read_safetensors(test::sdxl_model_dir() + "/unet/diffusion_pytorch_model.safetensors");
  ASSERT_TRUE(unet.ok());
  unet->erase("mid_block.resnets.1.conv2.weight");
  ASSERT_TRUE(sdxl::write_safetensors((dir_ / "copy/unet/diffusion_pytorch_model.safetensors").string(), *unet).ok());
  const auto broken = make_generator("sdxl", options_json((dir_ / "copy").string()));
  EXPECT_TRUE(contains_all(std::string(broken.status().message()),
                           {"not a usable SDXL model", "unet", "1 missing: mid_block.resnets.1.conv2.weight"}));

  // A refiner-style index (aesthetic-score conditioning) is refused by name.
  std::ifstream index_in(test::sdxl_model_dir() + "/model_index.json");
  nlohmann::json index = nlohmann::json::parse(index_in);
  index["requires_aesthetics_score"] = true;
  write("copy/model_index.json", index.dump());
  EXPECT_TRUE(
      contains_all(std::string(make_generator("sdxl", options_json((dir_ / "copy").string())).status().message()),
                   {"aesthetic-score"}));
}

}  // namespace
}  // namespace gaps

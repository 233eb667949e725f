// Scene adaptation by LoRA in the `sdxl` backend on the tiny fixture model: adapt() with lora_steps > 0
// trains adapters on the ground-truth views (with and without the tiny depth ControlNet) that change the
// generated images, saves them with lora_save, and a generator started with that file (option lora)
// generates the same images; the job's SceneAdaptation wins over the options (and a LoRA file over it, with
// a note); LoRA together with the IP-Adapter; the LoRA options' errors.
#include <string>

#include <ATen/ATen.h>
#include <ATen/CPUGeneratorImpl.h>
#include <gtest/gtest.h>

#include "common/safetensors.h"
#include "diffusion_worker/backend_registry.h"
#include "diffusion_worker/sdxl_generator.h"
#include "tests/sdxl_test_util.h"
#include "tests/test_util.h"

namespace gaps {
namespace {

using test::contains_all;

std::string options_json(const std::string& extra) {
  return "{\"weights\": \"" + test::sdxl_model_dir() + "\", \"steps\": 4, \"prompt\": \"a fern\"" + extra + "}";
}

std::string controlnet_dir() {
  return std::string(GAPS_TEST_SCRIPTS_DIR) + "/fixtures/sdxl_controlnet_tiny/controlnet";
}

std::vector<ReferenceView> views(int64_t count, int64_t h, int64_t w) {
  std::vector<ReferenceView> out(count);
  at::Generator g = at::make_generator<at::CPUGeneratorImpl>(17);
  for (auto& v : out) {
    v.image = at::rand({h, w, 3}, g);
    v.render_depth = 1 + at::rand({h, w}, g);
    v.render_alpha = at::ones({h, w});
  }
  return out;
}

GenerationRequest request() {
  GenerationRequest r;
  at::Generator g = at::make_generator<at::CPUGeneratorImpl>(3);
  r.render_rgb = at::rand({12, 8, 3}, g);
  r.render_depth = 1 + at::rand({12, 8}, g);
  r.render_alpha = at::ones({12, 8});
  r.strength = 0.75;
  r.control_scale = 0.8;
  r.seed = 5;
  return r;
}

at::Tensor generate_one(Generator& generator) {
  auto images = generator.generate({request()});
  EXPECT_TRUE(images.ok()) << images.status();
  return images.ok() ? (*images)[0] : at::Tensor();
}

class SdxlLoraGeneratorTest : public test::TempDirTest {
 protected:
  // Adapts a generator with extra options, checks that its images change, and that the saved LoRA
  // reproduces them in a fresh generator.
  void check_adaptation(const std::string& extra) {
    const std::string path = (dir_ / "scene_lora.safetensors").string();
    auto generator = make_generator(
        "sdxl", options_json(extra + ", \"lora_steps\": 3, \"lora_lr\": 0.01, \"lora_save\": \"" + path + "\""));
    ASSERT_TRUE(generator.ok()) << generator.status();
    const at::Tensor before = generate_one(**generator);
    ASSERT_TRUE((*generator)->adapt(views(2, 12, 8), std::nullopt).ok());
    const at::Tensor after = generate_one(**generator);
    EXPECT_GT((after - before).abs().max().item<double>(), 1e-3);
    // The adapters are merged into the UNet; adapting again (the next scene) starts from the base weights,
    // so the same views and seed give the same images again.
    ASSERT_TRUE((*generator)->adapt(views(2, 12, 8), std::nullopt).ok());
    test::expect_close(generate_one(**generator), after, 1e-6, "generator adapted a second time");

    // Trained adapters sit on the cross-attention layers only, as the paper places them.
    auto saved = sdxl::read_safetensors(path);
    ASSERT_TRUE(saved.ok()) << saved.status();
    EXPECT_FALSE(saved->empty());
    for (const auto& [key, tensor] : *saved) EXPECT_NE(key.find(".attn2."), std::string::npos) << key;

    auto reloaded = make_generator("sdxl", options_json(extra + ", \"lora\": \"" + path + "\""));
    ASSERT_TRUE(reloaded.ok()) << reloaded.status();
    test::expect_close(generate_one(**reloaded), after, 1e-6, "generator with the saved LoRA");
  }
};

TEST_F(SdxlLoraGeneratorTest, AdaptTrainsAdaptersThatChangeTheImagesAndReload) { check_adaptation(""); }

TEST_F(SdxlLoraGeneratorTest, AdaptTrainsWithDepthControl) {
  check_adaptation(", \"controlnet\": \"" + controlnet_dir() + "\"");
}

// The job's adaptation decides: its steps and rank train the same adapters as a generator whose options
// ask for them; 0 steps trains none and removes an earlier scene's adapters; out of range is refused.
TEST_F(SdxlLoraGeneratorTest, TheJobsAdaptationWinsOverTheOptions) {
  auto by_job = make_generator("sdxl", options_json(", \"lora_lr\": 0.01"));  // lora_steps 0: no adaptation
  auto by_options = make_generator("sdxl", options_json(", \"lora_steps\": 3, \"lora_rank\": 2, \"lora_lr\": 0.01"));
  ASSERT_TRUE(by_job.ok()) << by_job.status();
  ASSERT_TRUE(by_options.ok()) << by_options.status();
  const std::vector<ReferenceView> gt = views(2, 12, 8);
  const at::Tensor base = generate_one(**by_job);
  ASSERT_TRUE((*by_job)->adapt(gt, std::nullopt).ok());
  test::expect_close(generate_one(**by_job), base, 1e-6, "the options' 0 steps");

  ASSERT_TRUE((*by_job)->adapt(gt, SceneAdaptation{2, 3}).ok());
  EXPECT_TRUE((*by_job)->notes().empty());
  const at::Tensor adapted = generate_one(**by_job);
  EXPECT_GT((adapted - base).abs().max().item<double>(), 1e-3);
  ASSERT_TRUE((*by_options)->adapt(gt, std::nullopt).ok());
  test::expect_close(adapted, generate_one(**by_options), 1e-6, "3 steps of rank 2 asked by the job and the options");
  ASSERT_TRUE((*by_job)->adapt(gt, SceneAdaptation{2, 2}).ok());
  EXPECT_GT((generate_one(**by_job) - adapted).abs().max().item<double>(), 1e-5) << "2 steps are not 3";

  ASSERT_TRUE((*by_options)->adapt(gt, SceneAdaptation{2, 0}).ok());
  test::expect_close(generate_one(**by_options), base, 1e-6, "0 steps after an adapted scene");
  const absl::Status refused = (*by_job)->adapt(gt, SceneAdaptation{0, 3});
  EXPECT_EQ(refused.code(), absl::StatusCode::kInvalidArgument);
  EXPECT_TRUE(contains_all(std::string(refused.message()), {"lora_rank must be >= 1"})) << refused;
}

// One worker's trained adapters, exported and installed by another with the same weights, give that worker the
// first one's images without training (what a pool of workers shares); nothing to export without training;
// bytes that are not adapters of this UNet are refused, naming where they came from.
TEST_F(SdxlLoraGeneratorTest, AnotherGeneratorInstallsTheExportedAdaptersAndGivesTheSameImages) {
  const std::string common = ", \"controlnet\": \"" + controlnet_dir() + "\", \"lora_lr\": 0.01";
  auto trained = make_generator("sdxl", options_json(common));
  auto installing = make_generator("sdxl", options_json(common));
  ASSERT_TRUE(trained.ok()) << trained.status();
  ASSERT_TRUE(installing.ok()) << installing.status();
  const std::vector<ReferenceView> gt = views(2, 12, 8);
  ASSERT_TRUE((*trained)->adapt(gt, SceneAdaptation{2, 0}).ok());
  auto nothing = (*trained)->export_adaptation();
  ASSERT_TRUE(nothing.ok()) << nothing.status();
  EXPECT_TRUE(nothing->empty()) << "0 steps trained no adapters";

  const at::Tensor base = generate_one(**installing);
  ASSERT_TRUE((*trained)->adapt(gt, SceneAdaptation{2, 3}).ok());
  const at::Tensor adapted = generate_one(**trained);
  auto exported = (*trained)->export_adaptation();
  ASSERT_TRUE(exported.ok()) << exported.status();
  ASSERT_FALSE(exported->empty());
  ASSERT_TRUE((*installing)->install_adaptation(gt, SceneAdaptation{2, 3}, *exported).ok());
  EXPECT_TRUE(at::equal(generate_one(**installing), adapted)) << "the installed adapters give other images";
  EXPECT_GT((adapted - base).abs().max().item<double>(), 1e-3);

  // Installing again (the scene comes back after another) replaces the adapters, it does not add to them.
  ASSERT_TRUE((*installing)->install_adaptation(gt, SceneAdaptation{2, 3}, *exported).ok());
  EXPECT_TRUE(at::equal(generate_one(**installing), adapted));

  const absl::Status refused = (*installing)->install_adaptation(gt, SceneAdaptation{2, 3}, "not safetensors");
  EXPECT_EQ(refused.code(), absl::StatusCode::kInvalidArgument) << refused;
  EXPECT_TRUE(contains_all(std::string(refused.message()), {"the adapters another worker trained"})) << refused;
}

// A LoRA file attached at start-up stays: a job asking for LoRA steps trains none, and the note says so.
TEST_F(SdxlLoraGeneratorTest, ALoraFileAttachedAtStartUpStaysAndANoteSaysSo) {
  const std::string path = (dir_ / "scene_lora.safetensors").string();
  auto saving = make_generator("sdxl", options_json(", \"lora_lr\": 0.01, \"lora_save\": \"" + path + "\""));
  ASSERT_TRUE(saving.ok()) << saving.status();
  ASSERT_TRUE((*saving)->adapt(views(2, 12, 8), SceneAdaptation{4, 3}).ok());
  const at::Tensor saved = generate_one(**saving);
  auto loaded = make_generator("sdxl", options_json(", \"lora\": \"" + path + "\""));
  ASSERT_TRUE(loaded.ok()) << loaded.status();
  ASSERT_TRUE((*loaded)->adapt(views(2, 12, 8), SceneAdaptation{4, 50}).ok());
  EXPECT_EQ((*loaded)->notes(),
            std::vector<std::string>{"sdxl keeps the LoRA file attached at start-up (option lora: " + path +
                                     "): the 50 LoRA steps asked for were not trained"});
  test::expect_close(generate_one(**loaded), saved, 1e-6, "the file's adapters after a job asked for 50 steps");
  ASSERT_TRUE((*loaded)->adapt(views(2, 12, 8), SceneAdaptation{4, 0}).ok());
  EXPECT_TRUE((*loaded)->notes().empty());
  test::expect_close(generate_one(**loaded), saved, 1e-6, "the file's adapters after a job asked for none");
}

// With depth_anything, LoRA training conditions the ControlNet on Depth-Anything's depth of each view (the
// tiny random fixture model) instead of the views' rendered depth: the adapters, hence the images, differ.
TEST_F(SdxlLoraGeneratorTest, DepthAnythingGivesTheTrainingViewsTheirDepth) {
  const std::string depth_model = std::string(GAPS_TEST_SCRIPTS_DIR) + "/fixtures/depth_anything_tiny/model";
  const std::string common = ", \"controlnet\": \"" + controlnet_dir() + "\", \"lora_steps\": 3, \"lora_lr\": 0.01";
  auto rendered = make_generator("sdxl", options_json(common));
  auto estimated = make_generator("sdxl", options_json(common + ", \"depth_anything\": \"" + depth_model + "\""));
  ASSERT_TRUE(rendered.ok()) << rendered.status();
  ASSERT_TRUE(estimated.ok()) << estimated.status();
  EXPECT_EQ((*rendered)->name(), "sdxl 1 controlnet lora-depth:rendered");
  EXPECT_EQ((*estimated)->name(), "sdxl 1 controlnet lora-depth:depth-anything");
  EXPECT_EQ((*estimated)->weights_identity(),
            "sdxl=" + test::sdxl_model_dir() + "\ncontrolnet=" + controlnet_dir() + "\ndepth_anything=" + depth_model);
  std::vector<ReferenceView> gt = views(2, 12, 8);
  ASSERT_TRUE((*rendered)->adapt(gt, std::nullopt).ok());
  for (auto& v : gt) v.render_depth = v.render_alpha = at::Tensor();  // not needed with Depth-Anything
  const absl::Status adapted = (*estimated)->adapt(gt, std::nullopt);
  ASSERT_TRUE(adapted.ok()) << adapted;
  EXPECT_GT((generate_one(**estimated) - generate_one(**rendered)).abs().max().item<double>(), 1e-4);
}

// The paper's full stack: LoRA adapted with the IP-Adapter and ControlNet loaded, then generation with all
// three. Training runs with the image branch off, so its adapters equal those of a generator without the
// IP-Adapter (same images for a request without reference views, where the image branch has scale 0); a
// reference view still changes the adapted generator's images.
TEST_F(SdxlLoraGeneratorTest, AdaptsWithTheIpAdapterLoadedAndGeneratesWithBoth) {
  const std::string ip_dir = std::string(GAPS_TEST_SCRIPTS_DIR) + "/fixtures/ip_adapter_tiny";
  const std::string ip = ", \"ip_adapter\": \"" + ip_dir + "/ip_adapter.safetensors\", \"image_encoder\": \"" + ip_dir +
                         "/image_encoder\", \"ip_adapter_scale\": 0.7";
  const std::string common = ", \"controlnet\": \"" + controlnet_dir() + "\", \"lora_steps\": 3, \"lora_lr\": 0.01";
  auto full = make_generator("sdxl", options_json(common + ip));
  auto without_ip = make_generator("sdxl", options_json(common));
  ASSERT_TRUE(full.ok()) << full.status();
  ASSERT_TRUE(without_ip.ok()) << without_ip.status();
  GenerationRequest with_reference = request();
  ReferenceView nearest;
  nearest.image = at::rand({12, 8, 3}, at::make_generator<at::CPUGeneratorImpl>(8));
  with_reference.references = {nearest};
  const auto generate_both = [&](Generator& g) {
    auto images = g.generate({with_reference, request()});
    EXPECT_TRUE(images.ok()) << images.status();
    return images.ok() ? *images : std::vector<at::Tensor>(2);
  };
  const std::vector<at::Tensor> before = generate_both(**full);  // sets an image prompt before training

  const std::vector<ReferenceView> gt = views(2, 12, 8);
  const absl::Status adapted = (*full)->adapt(gt, std::nullopt);
  ASSERT_TRUE(adapted.ok()) << adapted;
  ASSERT_TRUE((*without_ip)->adapt(gt, std::nullopt).ok());
  const std::vector<at::Tensor> after = generate_both(**full);
  EXPECT_GT((after[0] - before[0]).abs().max().item<double>(), 1e-3) << "the adapters change the images";
  EXPECT_GT((after[0] - after[1]).abs().max().item<double>(), 1e-3) << "the image prompt still acts after adapting";
  test::expect_close(after[1], generate_one(**without_ip), 1e-5, "adapters trained with and without the IP-Adapter");
}

// Depth-Anything's maps of the views are cached: a second adapt on the same views computes none, other
// views miss, and a generator with the same depth_cache folder reads them instead of computing them.
TEST_F(SdxlLoraGeneratorTest, DepthAnythingMapsOfTheViewsAreCached) {
  const std::string depth_model = std::string(GAPS_TEST_SCRIPTS_DIR) + "/fixtures/depth_anything_tiny/model";
  const std::string json =
      options_json(", \"controlnet\": \"" + controlnet_dir() + "\", \"lora_steps\": 1, " + "\"depth_anything\": \"" +
                   depth_model + "\", \"depth_cache\": \"" + (dir_ / "depth").string() + "\"");
  auto options = parse_sdxl_options(json);
  ASSERT_TRUE(options.ok()) << options.status();
  auto generator = SdxlGenerator::create(*options);
  ASSERT_TRUE(generator.ok()) << generator.status();
  const std::vector<ReferenceView> gt = views(2, 12, 8);
  ASSERT_TRUE((*generator)->adapt(gt, std::nullopt).ok());
  EXPECT_EQ((*generator)->depth_cache().computed(), 2);
  ASSERT_TRUE((*generator)->adapt(gt, std::nullopt).ok());
  EXPECT_EQ((*generator)->depth_cache().computed(), 2) << "the same views again";
  std::vector<ReferenceView> changed = gt;
  changed[1].image = 1 - changed[1].image;
  ASSERT_TRUE((*generator)->adapt(changed, std::nullopt).ok());
  EXPECT_EQ((*generator)->depth_cache().computed(), 3) << "only the changed view misses";

  auto restarted = SdxlGenerator::create(*options);
  ASSERT_TRUE(restarted.ok()) << restarted.status();
  ASSERT_TRUE((*restarted)->adapt(gt, std::nullopt).ok());
  EXPECT_EQ((*restarted)->depth_cache().computed(), 0);
  EXPECT_EQ((*restarted)->depth_cache().disk_reads(), 2);
  EXPECT_TRUE(contains_all(std::string(parse_sdxl_options(options_json(", \"depth_cache\": \"d\"")).status().message()),
                           {"depth_cache", "depth_anything"}));
}

TEST_F(SdxlLoraGeneratorTest, LoraOptionsAndViewsAreChecked) {
  const auto error = [](const std::string& extra) {
    auto generator = make_generator("sdxl", options_json(extra));
    return generator.ok() ? std::string("accepted") : std::string(generator.status().message());
  };
  EXPECT_TRUE(contains_all(error(", \"lora_save\": \"x.safetensors\", \"lora\": \"y.safetensors\""),
                           {"lora_save", "nothing is trained"}));
  EXPECT_TRUE(contains_all(error(", \"lora_steps\": -1"), {"lora_steps", ">= 0"}));
  EXPECT_TRUE(contains_all(error(", \"lora_rank\": 0"), {"lora_rank"}));
  EXPECT_TRUE(contains_all(error(", \"lora_lr\": 0"), {"lora_lr"}));
  EXPECT_TRUE(contains_all(error(", \"lora_steps\": 2, \"lora\": \"x.safetensors\""), {"lora", "not both"}));
  EXPECT_TRUE(contains_all(error(", \"depth_anything\": \"d\""), {"depth_anything", "controlnet"}));
  EXPECT_TRUE(contains_all(error(", \"controlnet\": \"" + controlnet_dir() +
                                 "\", \"lora_steps\": 2, \"depth_anything\": \"" + (dir_ / "absent").string() + "\""),
                           {"depth_anything", "absent"}));
  EXPECT_TRUE(contains_all(error(", \"lora\": \"" + (dir_ / "absent.safetensors").string() + "\""),
                           {"lora", "absent.safetensors"}));

  auto generator = make_generator("sdxl", options_json(", \"lora_steps\": 1"));
  ASSERT_TRUE(generator.ok()) << generator.status();
  std::vector<ReferenceView> mixed = views(2, 12, 8);
  mixed[1] = views(1, 10, 8)[0];
  const absl::Status status = (*generator)->adapt(mixed, std::nullopt);
  EXPECT_TRUE(contains_all(std::string(status.message()), {"one size", "view 1", "10x8"}));
}

}  // namespace
}  // namespace gaps

// Depth-Anything against transformers on a tiny random-weight model (tests/fixtures/depth_anything_tiny,
// made by tests/scripts/make_depth_anything_fixtures.py): preprocessing, backbone features, the raw
// forward and the post-processed depth; loading variants and refused configs; the depth cache.
#include "diffusion_worker/depth/depth_anything.h"

#include <filesystem>
#include <fstream>
#include <string>

#include <ATen/ATen.h>
#include <gtest/gtest.h>
#include "common/safetensors.h"
#include "diffusion_worker/depth/depth_cache.h"
#include "diffusion_worker/sdxl/model_folder.h"
#include "tests/sdxl_test_util.h"
#include "tests/test_util.h"

namespace gaps::depth {
namespace {

namespace fs = std::filesystem;
using test::contains_all;
using test::expect_close;

// fp32 on the CPU: max abs difference within 1e-4 of the reference's scale (max(1, max |reference|)).
constexpr double kTolerance = 1e-4;

std::string fixture_dir() { return std::string(GAPS_TEST_SCRIPTS_DIR) + "/fixtures/depth_anything_tiny"; }
std::string model_dir() { return fixture_dir() + "/model"; }

sdxl::TensorMap reference(const std::string& name) {
  auto tensors = sdxl::read_safetensors(fixture_dir() + "/reference/" + name + ".safetensors");
  EXPECT_TRUE(tensors.ok()) << tensors.status();
  return tensors.ok() ? *tensors : sdxl::TensorMap{};
}

nlohmann::json model_json(const std::string& file) {
  auto json = sdxl::read_json_file(model_dir() + "/" + file);
  EXPECT_TRUE(json.ok()) << json.status();
  return json.ok() ? *json : nlohmann::json();
}

sdxl::TensorMap model_weights() {
  auto weights = sdxl::read_folder_weights(model_dir());
  EXPECT_TRUE(weights.ok()) << weights.status();
  return weights.ok() ? *weights : sdxl::TensorMap{};
}

const DepthAnything& tiny_model() {
  static const DepthAnything* model = [] {
    auto loaded = DepthAnything::load(model_dir());
    EXPECT_TRUE(loaded.ok()) << loaded.status();
    return loaded.ok() ? new DepthAnything(std::move(*loaded)) : nullptr;
  }();
  if (model == nullptr) throw std::runtime_error("the tiny Depth-Anything fixture does not load");
  return *model;
}

absl::StatusOr<DepthAnything> from_config(const nlohmann::json& config, sdxl::TensorMap weights) {
  auto parsed = DepthAnythingConfig::from_json(config);
  if (!parsed.ok()) return parsed.status();
  auto processor = DepthProcessorConfig::from_json(model_json("preprocessor_config.json"));
  if (!processor.ok()) return processor.status();
  return DepthAnything::from_weights(*parsed, *processor, std::move(weights), {}, "test weights");
}

const char* const kImages[] = {"enlarged", "reduced"};

TEST(DepthAnythingConfigTest, ReadsTheFixtureConfig) {
  auto config = DepthAnythingConfig::from_json(model_json("config.json"));
  ASSERT_TRUE(config.ok()) << config.status();
  EXPECT_EQ(config->backbone.hidden_size, 32);
  EXPECT_EQ(config->backbone.num_hidden_layers, 4);
  EXPECT_EQ(config->backbone.mlp_hidden_size(), 64);
  EXPECT_EQ(config->backbone.out_indices, (std::vector<int64_t>{1, 2, 3, 4}));
  EXPECT_EQ(config->neck_hidden_sizes, (std::vector<int64_t>{8, 16, 24, 32}));
  EXPECT_EQ(config->reassemble_factors, (std::vector<double>{4, 2, 1, 0.5}));
  EXPECT_FALSE(config->metric);
  // Every tensor of the checkpoint is asked for, and nothing else.
  EXPECT_EQ(DepthAnything::weight_specs(*config).size(), model_weights().size());
}

TEST(DepthAnythingConfigTest, OutFeaturesStandInForOutIndices) {
  nlohmann::json config = model_json("config.json");
  config["backbone_config"].erase("out_indices");
  config["backbone_config"]["out_features"] = {"stem", "stage2", "stage3", "stage4"};
  auto parsed = DepthAnythingConfig::from_json(config);
  ASSERT_TRUE(parsed.ok()) << parsed.status();
  EXPECT_EQ(parsed->backbone.out_indices, (std::vector<int64_t>{0, 2, 3, 4}));
}

TEST(DepthAnythingConfigTest, NoBackboneConfigMeansDepthAnythingSmall) {
  auto parsed = DepthAnythingConfig::from_json(nlohmann::json::object());
  ASSERT_TRUE(parsed.ok()) << parsed.status();
  EXPECT_EQ(parsed->backbone.hidden_size, 384);
  EXPECT_EQ(parsed->backbone.num_attention_heads, 6);
  EXPECT_EQ(parsed->backbone.image_size, 518);
  EXPECT_EQ(parsed->backbone.out_indices, (std::vector<int64_t>{9, 10, 11, 12}));
}

// Each unsupported option is refused with an error that names it.
TEST(DepthAnythingConfigTest, RefusesUnsupportedOptionsByName) {
  const nlohmann::json base = model_json("config.json");
  const auto refused = [&](const std::function<void(nlohmann::json&)>& edit, const std::string& named) {
    nlohmann::json config = base;
    edit(config);
    const auto parsed = DepthAnythingConfig::from_json(config);
    ASSERT_FALSE(parsed.ok()) << named;
    EXPECT_TRUE(contains_all(std::string(parsed.status().message()), {named}));
  };
  refused([](auto& c) { c["backbone_config"]["use_swiglu_ffn"] = true; }, "use_swiglu_ffn");
  refused([](auto& c) { c["backbone_config"]["hidden_act"] = "relu"; }, "hidden_act 'relu'");
  refused([](auto& c) { c["backbone_config"]["model_type"] = "dinov2_with_registers"; }, "dinov2_with_registers");
  refused([](auto& c) { c["backbone_config"]["reshape_hidden_states"] = true; }, "reshape_hidden_states");
  refused([](auto& c) { c["backbone_config"]["num_channels"] = 4; }, "num_channels 4");
  refused([](auto& c) { c["backbone_config"]["image_size"] = {56, 70}; }, "image_size");
  refused([](auto& c) { c["backbone_config"]["out_indices"] = {3, 2, 4, 1}; }, "out_indices");
  refused([](auto& c) { c["depth_estimation_type"] = "ordinal"; }, "depth_estimation_type 'ordinal'");
  refused([](auto& c) { c["reassemble_factors"] = {4, 2, 1.5, 0.5}; }, "reassemble factor 1.5");
  refused([](auto& c) { c["neck_hidden_sizes"] = {8, 16, 24}; }, "neck_hidden_sizes");
  refused([](auto& c) { c["reassemble_hidden_size"] = 64; }, "reassemble_hidden_size");
  refused([](auto& c) { c["head_in_index"] = 4; }, "head_in_index");
  refused([](auto& c) { c["backbone"] = "facebook/dinov2-small"; }, "backbone \"facebook/dinov2-small\"");
  refused([](auto& c) { c["model_type"] = "dpt"; }, "model_type 'dpt'");
}

TEST(DepthProcessorConfigTest, RefusesUnsupportedOptionsByName) {
  const nlohmann::json base = model_json("preprocessor_config.json");
  const auto refused = [&](const std::string& key, const nlohmann::json& value, const std::string& named) {
    nlohmann::json config = base;
    config[key] = value;
    const auto parsed = DepthProcessorConfig::from_json(config);
    ASSERT_FALSE(parsed.ok()) << key;
    EXPECT_TRUE(contains_all(std::string(parsed.status().message()), {named}));
  };
  refused("resample", 2, "resample 2");
  refused("do_pad", true, "do_pad");
  refused("do_center_crop", true, "do_center_crop");
  refused("size", {{"shortest_edge", 518}}, "size");
  refused("image_processor_type", "DPTImageProcessorPil", "DPTImageProcessorPil");
  refused("image_mean", {0.5, 0.5}, "image_mean");
}

TEST(DepthAnythingLoadTest, MissingMisshapedAndUnexpectedTensorsAreNamed) {
  sdxl::TensorMap weights = model_weights();
  weights.erase("neck.convs.2.weight");
  weights["head.conv3.bias"] = at::zeros({2});
  weights["head.conv4.weight"] = at::zeros({1});
  const auto model = from_config(model_json("config.json"), std::move(weights));
  ASSERT_FALSE(model.ok());
  EXPECT_TRUE(contains_all(
      std::string(model.status().message()),
      {"test weights", "1 missing: neck.convs.2.weight [8, 24, 3, 3]",
       "1 mis-shaped: head.conv3.bias (checkpoint [2], config expects [1])", "1 unexpected: head.conv4.weight"}));
}

class DepthAnythingFolderTest : public test::TempDirTest {};

TEST_F(DepthAnythingFolderTest, AFolderWithoutProcessorConfigIsRefused) {
  fs::copy_file(model_dir() + "/config.json", dir_ / "config.json");
  fs::copy_file(model_dir() + "/model.safetensors", dir_ / "model.safetensors");
  const auto model = DepthAnything::load(dir_.string());
  ASSERT_FALSE(model.ok());
  EXPECT_TRUE(contains_all(std::string(model.status().message()), {"preprocessor_config.json"}));
}

TEST_F(DepthAnythingFolderTest, UnsupportedConfigInTheFolderIsNamed) {
  nlohmann::json config = model_json("config.json");
  config["backbone_config"]["use_swiglu_ffn"] = true;
  write("config.json", config.dump());
  fs::copy_file(model_dir() + "/preprocessor_config.json", dir_ / "preprocessor_config.json");
  const auto model = DepthAnything::load(dir_.string());
  ASSERT_FALSE(model.ok());
  EXPECT_TRUE(contains_all(std::string(model.status().message()), {dir_.string(), "use_swiglu_ffn"}));
}

// A sharded fp16 checkpoint (two files) loads, converted to float32.
TEST_F(DepthAnythingFolderTest, ShardedHalfPrecisionFolderLoads) {
  fs::copy_file(model_dir() + "/config.json", dir_ / "config.json");
  fs::copy_file(model_dir() + "/preprocessor_config.json", dir_ / "preprocessor_config.json");
  sdxl::TensorMap backbone, rest;
  for (const auto& [name, tensor] : model_weights()) {
    (name.rfind("backbone.", 0) == 0 ? backbone : rest)[name] = tensor.to(at::kHalf);
  }
  ASSERT_TRUE(sdxl::write_safetensors((dir_ / "model-00001-of-00002.safetensors").string(), backbone).ok());
  ASSERT_TRUE(sdxl::write_safetensors((dir_ / "model-00002-of-00002.safetensors").string(), rest).ok());
  auto model = DepthAnything::load(dir_.string());
  ASSERT_TRUE(model.ok()) << model.status();
  const sdxl::TensorMap ref = reference("enlarged");
  const at::Tensor depth = model->forward(ref.at("pixel_values"));
  EXPECT_EQ(depth.scalar_type(), at::kFloat);
  // The weights' fp16 rounding is all that differs.
  expect_close(depth, ref.at("predicted_depth"), 1e-2, "fp16 weights");
}

// DPT's resize rule: aspect kept by the side scaled least, sides rounded half to even to the multiple.
TEST(DepthProcessorTest, InputSizeFollowsTheResizeRule) {
  const DepthProcessor& p = tiny_model().processor();
  EXPECT_EQ(p.input_size(45, 61), (std::pair<int64_t, int64_t>{56, 70}));
  EXPECT_EQ(p.input_size(100, 77), (std::pair<int64_t, int64_t>{84, 70}));
  DepthProcessorConfig exact;
  exact.height = 35;
  exact.width = 21;
  exact.ensure_multiple_of = 14;
  // 35 / 14 = 2.5 and 21 / 14 = 1.5: both round to 2 patches (Python's round), not 3 and 2.
  EXPECT_EQ(DepthProcessor(exact).input_size(35, 21), (std::pair<int64_t, int64_t>{28, 28}));
}

TEST(DepthProcessorTest, PixelValuesMatchTransformers) {
  for (const char* name : kImages) {
    const sdxl::TensorMap ref = reference(name);
    const at::Tensor image = ref.at("image");
    auto pixels = tiny_model().processor().preprocess(image);
    ASSERT_TRUE(pixels.ok()) << pixels.status();
    expect_close(*pixels, ref.at("pixel_values"), 1e-5, std::string(name) + " pixel values");
    // A float image in [0, 1] holding the same 8-bit values is processed identically.
    auto from_float = tiny_model().processor().preprocess(image.to(at::kFloat) / 255);
    ASSERT_TRUE(from_float.ok()) << from_float.status();
    EXPECT_TRUE(at::equal(*from_float, *pixels)) << name;
  }
}

TEST(DepthProcessorTest, BadImagesAreRefused) {
  EXPECT_FALSE(tiny_model().processor().preprocess(at::zeros({8, 8}, at::kByte)).ok());
  EXPECT_FALSE(tiny_model().processor().preprocess(at::zeros({8, 8, 4}, at::kByte)).ok());
  EXPECT_FALSE(tiny_model().processor().preprocess(at::zeros({8, 8, 3}, at::kInt)).ok());
}

TEST(DepthAnythingParityTest, BackboneFeaturesMatchTransformers) {
  for (const char* name : kImages) {
    const sdxl::TensorMap ref = reference(name);
    const std::vector<at::Tensor> features = tiny_model().backbone_features(ref.at("pixel_values"));
    ASSERT_EQ(features.size(), 4u);
    for (size_t i = 0; i < features.size(); ++i) {
      expect_close(features[i], ref.at("feature_map." + std::to_string(i)), kTolerance,
                   std::string(name) + " feature map " + std::to_string(i));
    }
  }
}

TEST(DepthAnythingParityTest, ForwardMatchesTransformers) {
  for (const char* name : kImages) {
    const sdxl::TensorMap ref = reference(name);
    expect_close(tiny_model().forward(ref.at("pixel_values")), ref.at("predicted_depth"), kTolerance,
                 std::string(name) + " predicted depth");
  }
}

TEST(DepthAnythingParityTest, NativePatchGridAndBatchMatchTransformers) {
  const sdxl::TensorMap ref = reference("native_grid_batch");
  expect_close(tiny_model().forward(ref.at("pixel_values")), ref.at("predicted_depth"), kTolerance,
               "native grid batch");
}

TEST(DepthAnythingParityTest, EstimateDepthMatchesTheProcessorPipeline) {
  for (const char* name : kImages) {
    const sdxl::TensorMap ref = reference(name);
    auto depth = tiny_model().estimate_depth(ref.at("image"));
    ASSERT_TRUE(depth.ok()) << depth.status();
    EXPECT_EQ(depth->scalar_type(), at::kFloat);
    expect_close(*depth, ref.at("post_processed_depth"), kTolerance, std::string(name) + " estimated depth");
  }
}

TEST(DepthAnythingParityTest, MetricHeadMatchesTransformers) {
  nlohmann::json config = model_json("config.json");
  config["depth_estimation_type"] = "metric";
  config["max_depth"] = 5;
  auto model = from_config(config, model_weights());
  ASSERT_TRUE(model.ok()) << model.status();
  const sdxl::TensorMap ref = reference("metric");
  expect_close(model->forward(ref.at("pixel_values")), ref.at("predicted_depth"), kTolerance, "metric depth");
}

// Current transformers module names (attention.q_proj ...) load like the published layout.
TEST(DepthAnythingParityTest, CurrentAttentionNamesLoadAlike) {
  // The fixture holds the published names, so the other parity tests cover those.
  ASSERT_EQ(model_weights().count("backbone.encoder.layer.0.attention.attention.query.weight"), 1u);
  auto model = from_config(model_json("config.json"), rename_legacy_dinov2_names(model_weights()));
  ASSERT_TRUE(model.ok()) << model.status();
  const sdxl::TensorMap ref = reference("enlarged");
  expect_close(model->forward(ref.at("pixel_values")), ref.at("predicted_depth"), kTolerance, "renamed weights");
}

class DepthCacheTest : public test::TempDirTest {};

DepthCache::Compute counting(int* calls, at::Tensor map) {
  return [calls, map]() -> absl::StatusOr<at::Tensor> {
    ++*calls;
    return map;
  };
}

TEST_F(DepthCacheTest, ComputesEachViewOnceInMemory) {
  DepthCache cache;
  int calls = 0;
  const at::Tensor a = at::rand({4, 5}), b = at::rand({4, 5});
  for (int round = 0; round < 3; ++round) {
    auto first = cache.get_or_compute("fern", "view_0", 4, 5, counting(&calls, a));
    auto second = cache.get_or_compute("fern", "view_1", 4, 5, counting(&calls, b));
    ASSERT_TRUE(first.ok() && second.ok());
    EXPECT_TRUE(at::equal(*first, a));
    EXPECT_TRUE(at::equal(*second, b));
  }
  EXPECT_EQ(calls, 2);
  EXPECT_EQ(cache.computed(), 2);
  // Another scene with the same view id is another map.
  ASSERT_TRUE(cache.get_or_compute("bonsai", "view_0", 4, 5, counting(&calls, b)).ok());
  EXPECT_EQ(calls, 3);
  cache.forget_scene("fern");
  auto again = cache.get_or_compute("fern", "view_0", 4, 5, counting(&calls, b));
  ASSERT_TRUE(again.ok());
  EXPECT_EQ(calls, 4);
  EXPECT_TRUE(at::equal(*again, b));
}

TEST_F(DepthCacheTest, AFolderKeepsMapsAcrossCaches) {
  const at::Tensor map = at::rand({6, 7});
  int calls = 0;
  {
    DepthCache cache(dir_.string());
    ASSERT_TRUE(cache.get_or_compute("fern", "IMG_4026.JPG", 6, 7, counting(&calls, map)).ok());
  }
  EXPECT_TRUE(fs::exists(dir_ / "fern" / "IMG_4026.JPG.npy"));
  DepthCache reopened(dir_.string());
  auto read = reopened.get_or_compute("fern", "IMG_4026.JPG", 6, 7, counting(&calls, at::zeros({6, 7})));
  ASSERT_TRUE(read.ok()) << read.status();
  EXPECT_EQ(calls, 1);
  EXPECT_EQ(reopened.disk_reads(), 1);
  EXPECT_TRUE(at::equal(*read, map));  // float32 on disk: bit-exact
  // A stored map of another size is stale and computed afresh (and replaces the file).
  const at::Tensor larger = at::rand({8, 9});
  auto recomputed = reopened.get_or_compute("fern", "IMG_4026.JPG", 8, 9, counting(&calls, larger));
  ASSERT_TRUE(recomputed.ok()) << recomputed.status();
  EXPECT_EQ(calls, 2);
  EXPECT_TRUE(at::equal(*recomputed, larger));
  DepthCache third(dir_.string());
  ASSERT_TRUE(third.get_or_compute("fern", "IMG_4026.JPG", 8, 9, counting(&calls, at::zeros({8, 9}))).ok());
  EXPECT_EQ(calls, 2);
}

TEST_F(DepthCacheTest, RefusesBadIdsFailedAndMisSizedComputations) {
  DepthCache cache(dir_.string());
  int calls = 0;
  const at::Tensor map = at::rand({2, 3});
  for (const std::string bad : {"", "..", "a/b", "with space"}) {
    const auto result = cache.get_or_compute("fern", bad, 2, 3, counting(&calls, map));
    ASSERT_FALSE(result.ok()) << bad;
    EXPECT_TRUE(contains_all(std::string(result.status().message()), {"view id '" + bad + "'"}));
  }
  EXPECT_FALSE(cache.get_or_compute("../x", "v", 2, 3, counting(&calls, map)).ok());
  EXPECT_EQ(calls, 0);

  const auto failed = cache.get_or_compute("fern", "v", 2, 3,
                                           [] { return absl::StatusOr<at::Tensor>(absl::InternalError("no model")); });
  ASSERT_FALSE(failed.ok());
  EXPECT_EQ(failed.status().message(), "no model");
  const auto mis_sized = cache.get_or_compute("fern", "v", 4, 3, counting(&calls, map));
  ASSERT_FALSE(mis_sized.ok());
  EXPECT_TRUE(contains_all(std::string(mis_sized.status().message()), {"fern/v", "4 x 3"}));
  EXPECT_FALSE(fs::exists(dir_ / "fern" / "v.npy"));  // nothing was stored for a failed computation
  // Unreadable stored files are an error, not a silent recomputation.
  write("fern/w.npy", "not an npy file");
  const auto corrupt = cache.get_or_compute("fern", "w", 2, 3, counting(&calls, map));
  ASSERT_FALSE(corrupt.ok());
  EXPECT_TRUE(contains_all(std::string(corrupt.status().message()), {"w.npy"}));
}

// The cache with the model, as the worker uses them: each ground-truth view's depth is estimated once.
TEST_F(DepthCacheTest, CachesEstimatedDepth) {
  DepthCache cache(dir_.string());
  const sdxl::TensorMap ref = reference("enlarged");
  const at::Tensor image = ref.at("image");
  const auto estimate = [&]() { return tiny_model().estimate_depth(image); };
  for (int round = 0; round < 2; ++round) {
    auto depth = cache.get_or_compute("scene", "0", image.size(0), image.size(1), estimate);
    ASSERT_TRUE(depth.ok()) << depth.status();
    expect_close(*depth, ref.at("post_processed_depth"), kTolerance, "cached depth");
  }
  EXPECT_EQ(cache.computed(), 1);
}

}  // namespace
}  // namespace gaps::depth

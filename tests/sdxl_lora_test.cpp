// LoRA on the SDXL UNet's attention projections against the tiny fixtures of tests/fixtures/lora_tiny (made by
// tests/scripts/make_lora_fixtures.py: a diffusers-saved rank-4 LoRA for the UNet of tests/fixtures/sdxl_tiny
// and torch references of PEFT's LoRA forward). fp32 on the CPU, max abs diff <= 1e-4 x max(1, max |ref|).
// Also: merging equals the adapted forward, save -> load is tensor-exact, fresh adapters go on the
// cross-attention layers only (the paper's placement) and leave the UNet's output unchanged, and malformed
// files are refused naming the tensor (the UNet left untouched).
#include <map>
#include <set>
#include <string>
#include <utility>

#include <ATen/ATen.h>
#include <gtest/gtest.h>

#include "absl/strings/str_cat.h"
#include "diffusion_worker/sdxl/lora.h"
#include "diffusion_worker/sdxl/model_folder.h"
#include "diffusion_worker/sdxl/unet.h"
#include "tests/sdxl_test_util.h"
#include "tests/test_util.h"

namespace gaps {
namespace {

using sdxl::TensorMap;
using sdxl::UNetLora;
using test::contains_all;
using test::expect_close;

constexpr double kTolerance = 1e-4;
constexpr char kPatternModule[] = "mid_block.attentions.0.transformer_blocks.0.attn1.to_q";

std::string lora_fixture_dir() { return std::string(GAPS_TEST_SCRIPTS_DIR) + "/fixtures/lora_tiny"; }
std::string lora_file() { return lora_fixture_dir() + "/pytorch_lora_weights.safetensors"; }

TensorMap lora_reference(const std::string& name) {
  auto tensors = sdxl::read_safetensors(lora_fixture_dir() + "/reference/" + name + ".safetensors");
  EXPECT_TRUE(tensors.ok()) << tensors.status();
  return tensors.ok() ? *tensors : TensorMap{};
}

sdxl::UNet2DCondition tiny_unet() {
  const sdxl::ModelFolder f = *sdxl::ModelFolder::open(test::sdxl_model_dir());
  auto unet = sdxl::UNet2DCondition::load(*sdxl::UNetConfig::from_json(*f.read_json("unet")), *f.read_weights("unet"),
                                          at::TensorOptions(), "unet");
  EXPECT_TRUE(unet.ok()) << unet.status();
  return std::move(*unet);
}

at::Tensor unet_step(const sdxl::UNet2DCondition& unet) {
  return unet.forward(test::recorded_unet_inputs(test::sdxl_reference("unet")));
}

TEST(LoraTest, UNetStepMatchesPeftLoraForward) {
  sdxl::UNet2DCondition unet = tiny_unet();
  auto lora = UNetLora::load(lora_file(), unet);
  ASSERT_TRUE(lora.ok()) << lora.status();
  // The file adapts self- and cross-attention (12 transformer blocks x 2 layers x 4 projections); loading
  // attaches all of it, only new adapters are restricted to cross-attention.
  EXPECT_EQ(lora->adapters().size(), 96u);
  for (const auto& a : lora->adapters()) {
    EXPECT_EQ(a.down.size(0), 4) << a.module;
    EXPECT_DOUBLE_EQ(a.alpha, a.module == kPatternModule ? 2.0 : 8.0) << a.module;
  }
  const at::Tensor expected = lora_reference("unet_lora").at("out");
  const at::Tensor actual = unet_step(unet);
  expect_close(actual, expected, kTolerance, "UNet step with LoRA");
  RecordProperty("max_abs_diff", absl::StrCat((actual - expected).abs().max().item<double>()));
  // The adapters matter: without them the output is the base UNet's.
  lora->detach_from(unet);
  expect_close(unet_step(unet), test::sdxl_reference("unet").at("out"), kTolerance, "UNet step after detaching");
  EXPECT_GT((unet_step(unet) - expected).abs().max().item<double>(), 0.1);
}

TEST(LoraTest, MergedWeightsGiveTheAdaptedOutput) {
  sdxl::UNet2DCondition unet = tiny_unet();
  auto lora = UNetLora::load(lora_file(), unet);
  ASSERT_TRUE(lora.ok()) << lora.status();
  lora->merge_into(unet);
  const at::Tensor actual = unet_step(unet), expected = lora_reference("unet_lora").at("out");
  expect_close(actual, expected, kTolerance, "UNet step with merged LoRA");
  RecordProperty("max_abs_diff", absl::StrCat((actual - expected).abs().max().item<double>()));
}

TEST(LoraTest, UnmergingRestoresTheBaseWeightsBitForBit) {
  sdxl::UNet2DCondition unet = tiny_unet();
  const at::Tensor base = unet_step(unet);
  std::vector<at::Tensor> before;
  unet.for_each_attention([&](const std::string&, sdxl::Attention& a) { before.push_back(a.to_q.weight.clone()); });
  auto lora = UNetLora::load(lora_file(), unet);
  ASSERT_TRUE(lora.ok()) << lora.status();
  lora->merge_into(unet);
  EXPECT_TRUE(lora->merged());
  lora->merge_into(unet);  // a second merge must not add the adapters twice
  expect_close(unet_step(unet), lora_reference("unet_lora").at("out"), kTolerance, "UNet step after two merges");
  lora->unmerge_from(unet);
  EXPECT_FALSE(lora->merged());
  size_t i = 0;
  unet.for_each_attention([&](const std::string& name, sdxl::Attention& a) {
    EXPECT_TRUE(at::equal(a.to_q.weight, before[i++])) << name;
    EXPECT_FALSE(a.to_q.lora_down.defined()) << name;
  });
  EXPECT_TRUE(at::equal(unet_step(unet), base));
}

// A pipeline merging scene after scene keeps one host copy of the base weights: the second scene's merge reuses
// the first's copies, and unmerging either restores the base weights bit for bit.
TEST(LoraTest, MergesThatShareBaseCopiesCopyTheWeightsOnceAndStillRestoreThem) {
  sdxl::UNet2DCondition unet = tiny_unet();
  const at::Tensor base = unet_step(unet);
  UNetLora::BaseCopies copies;
  auto first = UNetLora::load(lora_file(), unet);
  ASSERT_TRUE(first.ok()) << first.status();
  first->merge_into(unet, &copies);
  ASSERT_EQ(copies.size(), first->adapters().size());
  std::map<std::string, const void*> kept;
  for (const auto& [module, copy] : copies) kept[module] = copy.const_data_ptr();
  first->unmerge_from(unet);
  EXPECT_TRUE(at::equal(unet_step(unet), base));

  auto second = UNetLora::load(lora_file(), unet);
  ASSERT_TRUE(second.ok()) << second.status();
  second->merge_into(unet, &copies);
  expect_close(unet_step(unet), lora_reference("unet_lora").at("out"), kTolerance, "UNet step, second merge");
  for (const auto& [module, copy] : copies) EXPECT_EQ(copy.const_data_ptr(), kept.at(module)) << module;
  second->unmerge_from(unet);
  EXPECT_TRUE(at::equal(unet_step(unet), base));
}

bool is_cross_attention(const std::string& module) { return module.find(".attn2.") != std::string::npos; }

TEST(LoraTest, FreshAdaptersGoOnEveryCrossAttentionProjectionOnly) {
  sdxl::UNet2DCondition unet = tiny_unet();
  auto lora = UNetLora::create(unet, {}, 11);
  ASSERT_TRUE(lora.ok()) << lora.status();
  std::set<std::string> adapted;
  for (const auto& a : lora->adapters()) {
    EXPECT_TRUE(is_cross_attention(a.module)) << a.module;
    adapted.insert(a.module);
  }
  int cross_layers = 0;
  unet.for_each_attention([&](const std::string& name, sdxl::Attention& attn) {
    const bool cross = is_cross_attention(name + ".");
    cross_layers += cross ? 1 : 0;
    for (const auto& [suffix, layer] : {std::pair<std::string, sdxl::Linear*>{"to_q", &attn.to_q},
                                        {"to_k", &attn.to_k},
                                        {"to_v", &attn.to_v},
                                        {"to_out.0", &attn.to_out}}) {
      EXPECT_EQ(adapted.count(name + "." + suffix), cross ? 1u : 0u) << name << "." << suffix;
      EXPECT_EQ(layer->lora_down.defined(), cross) << name << "." << suffix;
    }
  });
  EXPECT_EQ(cross_layers, 12);
  EXPECT_EQ(lora->adapters().size(), 4u * cross_layers);
}

TEST(LoraTest, FreshAdaptersLeaveTheOutputUnchangedAndFollowTheSeed) {
  sdxl::UNet2DCondition unet = tiny_unet();
  const at::Tensor base = unet_step(unet);
  sdxl::LoraConfig config;
  config.targets = {"to_q", "to_v"};
  auto lora = UNetLora::create(unet, config, 11);
  ASSERT_TRUE(lora.ok()) << lora.status();
  EXPECT_EQ(lora->adapters().size(), 24u);  // 12 cross-attention layers x 2 projections
  EXPECT_TRUE(at::equal(unet_step(unet), base));
  sdxl::UNet2DCondition other = tiny_unet();
  auto again = UNetLora::create(other, config, 11);
  ASSERT_TRUE(again.ok()) << again.status();
  for (size_t i = 0; i < lora->adapters().size(); ++i) {
    const auto& a = lora->adapters()[i];
    EXPECT_TRUE(at::equal(a.down, again->adapters()[i].down)) << a.module;
    EXPECT_LE(a.down.abs().max().item<double>(), 1.0 / std::sqrt(static_cast<double>(a.down.size(1))));
    EXPECT_EQ(a.up.abs().max().item<double>(), 0.0);
  }
  config.targets = {"to_x"};
  EXPECT_TRUE(contains_all(std::string(UNetLora::create(other, config, 1).status().message()), {"to_x"}));
}

class LoraFileTest : public test::TempDirTest {};

TEST_F(LoraFileTest, SaveLoadRoundTripIsExact) {
  sdxl::UNet2DCondition unet = tiny_unet();
  auto lora = UNetLora::load(lora_file(), unet);
  ASSERT_TRUE(lora.ok()) << lora.status();
  const std::string path = (dir_ / "lora.safetensors").string();
  ASSERT_TRUE(lora->save(path).ok());
  const TensorMap original = *sdxl::read_safetensors(lora_file()), saved = *sdxl::read_safetensors(path);
  ASSERT_EQ(saved.size(), original.size());
  for (const auto& [key, tensor] : original) {
    ASSERT_TRUE(saved.count(key)) << key;
    EXPECT_TRUE(at::equal(saved.at(key), tensor)) << key;
  }
  sdxl::UNet2DCondition reloaded_unet = tiny_unet();
  auto reloaded = UNetLora::load(path, reloaded_unet);
  ASSERT_TRUE(reloaded.ok()) << reloaded.status();
  for (size_t i = 0; i < lora->adapters().size(); ++i) {
    EXPECT_EQ(reloaded->adapters()[i].module, lora->adapters()[i].module);
    EXPECT_EQ(reloaded->adapters()[i].alpha, lora->adapters()[i].alpha) << lora->adapters()[i].module;
  }
  EXPECT_TRUE(at::equal(unet_step(reloaded_unet), unet_step(unet)));
}

TEST(LoraTest, WithoutMetadataAlphaIsTheRank) {
  sdxl::UNet2DCondition unet = tiny_unet();
  auto lora = UNetLora::from_tensors(*sdxl::read_safetensors(lora_file()), {}, unet, "bare");
  ASSERT_TRUE(lora.ok()) << lora.status();
  for (const auto& a : lora->adapters()) EXPECT_DOUBLE_EQ(a.scale(), 1.0) << a.module;
}

::testing::AssertionResult refused(TensorMap tensors, std::initializer_list<std::string> parts) {
  sdxl::UNet2DCondition unet = tiny_unet();
  const at::Tensor base = unet_step(unet);
  auto lora = UNetLora::from_tensors(tensors, {}, unet, "broken.safetensors");
  if (lora.ok()) return ::testing::AssertionFailure() << "loaded";
  if (!at::equal(unet_step(unet), base)) return ::testing::AssertionFailure() << "the UNet was changed";
  return contains_all(std::string(lora.status().message()), parts);
}

TEST(LoraTest, MalformedFilesAreRefusedNamingTheTensor) {
  const TensorMap good = *sdxl::read_safetensors(lora_file());
  const std::string module = "unet.up_blocks.0.attentions.1.transformer_blocks.0.attn2.to_k";
  TensorMap missing = good;
  missing.erase(module + ".lora_B.weight");
  EXPECT_TRUE(refused(missing, {"broken.safetensors", "missing", module + ".lora_B.weight"}));
  TensorMap misshaped = good;
  misshaped[module + ".lora_A.weight"] = at::zeros({4, 63});
  EXPECT_TRUE(refused(misshaped, {"mis-shaped", module + ".lora_A.weight", "[4, 63]", "[rank, 64]"}));
  TensorMap rank_mismatch = good;
  rank_mismatch[module + ".lora_B.weight"] = at::zeros({32, 3});
  EXPECT_TRUE(refused(rank_mismatch, {"mis-shaped", module + ".lora_B.weight", "[32, 3]", "[32, 4]"}));
  TensorMap unknown = good;
  unknown["unet.down_blocks.0.attentions.0.transformer_blocks.0.attn1.to_q.lora_A.weight"] = at::zeros({4, 16});
  EXPECT_TRUE(refused(unknown, {"no attention projection", "down_blocks.0.attentions.0"}));
  TensorMap text = good;
  text["text_encoder.text_model.encoder.layers.0.self_attn.q_proj.lora_A.weight"] = at::zeros({4, 32});
  EXPECT_TRUE(refused(text, {"text encoder", "q_proj"}));
  TensorMap kohya;
  kohya["lora_unet_mid_block_attentions_0_transformer_blocks_0_attn1_to_q.lora_down.weight"] = at::zeros({4, 32});
  EXPECT_TRUE(refused(kohya, {"kohya"}));
  EXPECT_TRUE(refused({}, {"no adapters"}));
}

}  // namespace
}  // namespace gaps

// Parity of the SDXL components with diffusers/transformers on the tiny random-weight fixtures
// (tests/fixtures/sdxl_tiny, made by tests/scripts/make_sdxl_fixtures.py). fp32 on the CPU; tolerance:
// max abs diff <= 1e-4 x max(1, max |reference|) (float32 summation order differs between the two).
#include <fstream>

#include <ATen/ATen.h>
#include <gtest/gtest.h>
#include <nlohmann/json.hpp>

#include "diffusion_worker/sdxl/clip_text_encoder.h"
#include "diffusion_worker/sdxl/clip_tokenizer.h"
#include "diffusion_worker/sdxl/model_folder.h"
#include "diffusion_worker/sdxl/unet.h"
#include "diffusion_worker/sdxl/vae.h"
#include "tests/sdxl_test_util.h"

namespace gaps::sdxl {
namespace {

constexpr double kTolerance = 1e-4;
using test::expect_close;

ModelFolder folder() {
  auto f = ModelFolder::open(test::sdxl_model_dir());
  EXPECT_TRUE(f.ok()) << f.status();
  return *f;
}

TEST(ClipTokenizerTest, MatchesTransformersIds) {
  std::ifstream in(test::sdxl_fixture_dir() + "/reference/tokenizer.json");
  const nlohmann::json ref = nlohmann::json::parse(in);
  for (const char* name : {"tokenizer", "tokenizer_2"}) {
    auto tok = ClipTokenizer::load(test::sdxl_model_dir() + "/" + name);
    ASSERT_TRUE(tok.ok()) << tok.status();
    for (size_t i = 0; i < ref["prompts"].size(); ++i) {
      EXPECT_EQ(tok->encode(ref["prompts"][i].get<std::string>(), 77), ref[name][i].get<std::vector<int64_t>>())
          << name << " on '" << ref["prompts"][i].get<std::string>() << "'";
    }
  }
}

TEST(ClipTokenizerTest, TruncatesLongPromptsKeepingEndOfText) {
  auto tok = ClipTokenizer::load(test::sdxl_model_dir() + "/tokenizer");
  ASSERT_TRUE(tok.ok());
  std::string long_prompt;
  for (int i = 0; i < 100; ++i) long_prompt += "fern ";
  const auto ids = tok->encode(long_prompt, 77);
  ASSERT_EQ(ids.size(), 77u);
  EXPECT_EQ(ids.front(), tok->bos_id());
  EXPECT_EQ(ids.back(), tok->eos_id());
}

void check_text_encoder(const std::string& component, bool with_projection) {
  const ModelFolder f = folder();
  auto config = ClipTextConfig::from_json(*f.read_json(component));
  ASSERT_TRUE(config.ok()) << config.status();
  auto encoder =
      ClipTextEncoder::load(*config, with_projection, *f.read_weights(component), at::TensorOptions(), component);
  ASSERT_TRUE(encoder.ok()) << encoder.status();
  const TensorMap ref = test::sdxl_reference(component);
  const ClipTextOutput out = encoder->forward(ref.at("input_ids"));
  expect_close(out.penultimate, ref.at("penultimate"), kTolerance, component + " penultimate hidden states");
  expect_close(out.last_hidden_state, ref.at("last_hidden_state"), kTolerance, component + " last hidden state");
  if (with_projection) {
    expect_close(out.text_embeds, ref.at("text_embeds"), kTolerance, component + " projected pooled output");
  } else {
    expect_close(out.pooled, ref.at("pooled"), kTolerance, component + " pooled output");
  }
}

TEST(ClipTextEncoderTest, MatchesCLIPTextModel) { check_text_encoder("text_encoder", false); }
TEST(ClipTextEncoderTest, MatchesCLIPTextModelWithProjection) { check_text_encoder("text_encoder_2", true); }

TEST(ClipTextEncoderTest, ProjectionWithoutItsWeightIsAnError) {
  const ModelFolder f = folder();
  auto config = ClipTextConfig::from_json(*f.read_json("text_encoder"));
  auto encoder =
      ClipTextEncoder::load(*config, true, *f.read_weights("text_encoder"), at::TensorOptions(), "text_encoder");
  ASSERT_FALSE(encoder.ok());
  EXPECT_TRUE(test::contains_all(std::string(encoder.status().message()), {"text_projection.weight"}));
}

TEST(AutoencoderKLTest, MatchesDiffusersEncoderAndDecoder) {
  const ModelFolder f = folder();
  auto config = VaeConfig::from_json(*f.read_json("vae"));
  ASSERT_TRUE(config.ok()) << config.status();
  EXPECT_DOUBLE_EQ(config->scaling_factor, 0.13025);
  auto vae = AutoencoderKL::load(*config, *f.read_weights("vae"), at::TensorOptions(), "vae");
  ASSERT_TRUE(vae.ok()) << vae.status();
  const TensorMap ref = test::sdxl_reference("vae");
  expect_close(vae->encode_moments(ref.at("image")), ref.at("moments"), kTolerance, "VAE encoder moments");
  expect_close(vae->decode(ref.at("latents")), ref.at("decoded"), kTolerance, "VAE decoder");
}

TEST(AutoencoderKLTest, MisShapedConfigNamesTheTensors) {
  const ModelFolder f = folder();
  auto config = VaeConfig::from_json(*f.read_json("vae"));
  config->latent_channels = 8;
  auto vae = AutoencoderKL::load(*config, *f.read_weights("vae"), at::TensorOptions(), "vae");
  ASSERT_FALSE(vae.ok());
  EXPECT_TRUE(test::contains_all(std::string(vae.status().message()), {"mis-shaped", "quant_conv.weight"}));
}

TEST(UNet2DConditionTest, MatchesDiffusersWithTextTimeConditioning) {
  const ModelFolder f = folder();
  auto config = UNetConfig::from_json(*f.read_json("unet"));
  ASSERT_TRUE(config.ok()) << config.status();
  auto unet = UNet2DCondition::load(*config, *f.read_weights("unet"), at::TensorOptions(), "unet");
  ASSERT_TRUE(unet.ok()) << unet.status();
  const TensorMap ref = test::sdxl_reference("unet");
  expect_close(unet->forward(test::recorded_unet_inputs(ref)), ref.at("out"), kTolerance, "UNet output");
}

void expect_same_config(const UNetConfig& a, const UNetConfig& b, const std::string& what) {
  EXPECT_EQ(a.in_channels, b.in_channels) << what;
  EXPECT_EQ(a.out_channels, b.out_channels) << what;
  EXPECT_EQ(a.layers_per_block, b.layers_per_block) << what;
  EXPECT_EQ(a.norm_num_groups, b.norm_num_groups) << what;
  EXPECT_EQ(a.cross_attention_dim, b.cross_attention_dim) << what;
  EXPECT_EQ(a.block_out_channels, b.block_out_channels) << what;
  EXPECT_EQ(a.num_attention_heads, b.num_attention_heads) << what;
  EXPECT_EQ(a.transformer_layers_per_block, b.transformer_layers_per_block) << what;
  EXPECT_EQ(a.reverse_transformer_layers_per_block, b.reverse_transformer_layers_per_block) << what;
  EXPECT_EQ(a.down_block_types, b.down_block_types) << what;
  EXPECT_EQ(a.up_block_types, b.up_block_types) << what;
  EXPECT_EQ(a.norm_eps, b.norm_eps) << what;
  EXPECT_EQ(a.flip_sin_to_cos, b.flip_sin_to_cos) << what;
  EXPECT_EQ(a.use_linear_projection, b.use_linear_projection) << what;
  EXPECT_EQ(a.freq_shift, b.freq_shift) << what;
  EXPECT_EQ(a.addition_embed_type, b.addition_embed_type) << what;
  EXPECT_EQ(a.addition_time_embed_dim, b.addition_time_embed_dim) << what;
  EXPECT_EQ(a.projection_class_embeddings_input_dim, b.projection_class_embeddings_input_dim) << what;
}

// One set of defaults: a key left out of config.json reads as the default-constructed member, and those are
// the values diffusers' UNet2DConditionModel() writes to its config.json when given no arguments.
TEST(UNetConfigTest, AbsentKeysReadAsTheDefaultConstructedConfig) {
  auto empty = UNetConfig::from_json(nlohmann::json::object());
  ASSERT_TRUE(empty.ok()) << empty.status();
  expect_same_config(*empty, UNetConfig{}, "{}");

  const nlohmann::json diffusers_defaults = {
      {"in_channels", 4},
      {"out_channels", 4},
      {"flip_sin_to_cos", true},
      {"freq_shift", 0},
      {"down_block_types", {"CrossAttnDownBlock2D", "CrossAttnDownBlock2D", "CrossAttnDownBlock2D", "DownBlock2D"}},
      {"mid_block_type", "UNetMidBlock2DCrossAttn"},
      {"up_block_types", {"UpBlock2D", "CrossAttnUpBlock2D", "CrossAttnUpBlock2D", "CrossAttnUpBlock2D"}},
      {"only_cross_attention", false},
      {"block_out_channels", {320, 640, 1280, 1280}},
      {"layers_per_block", 2},
      {"norm_num_groups", 32},
      {"norm_eps", 1e-5},
      {"cross_attention_dim", 1280},
      {"transformer_layers_per_block", 1},
      {"reverse_transformer_layers_per_block", nullptr},
      {"attention_head_dim", 8},
      {"num_attention_heads", nullptr},
      {"use_linear_projection", false},
      {"addition_embed_type", nullptr},
      {"addition_time_embed_dim", nullptr},
      {"projection_class_embeddings_input_dim", nullptr}};
  auto written = UNetConfig::from_json(diffusers_defaults);
  ASSERT_TRUE(written.ok()) << written.status();
  expect_same_config(*written, UNetConfig{}, "diffusers' defaults written out");
}

TEST(UNetConfigTest, PerBlockDefaultsFollowTheBlockCount) {
  auto config = UNetConfig::from_json({{"block_out_channels", {32, 64}},
                                       {"down_block_types", {"DownBlock2D", "CrossAttnDownBlock2D"}},
                                       {"up_block_types", {"CrossAttnUpBlock2D", "UpBlock2D"}},
                                       {"transformer_layers_per_block", {1, 3}}});
  ASSERT_TRUE(config.ok()) << config.status();
  EXPECT_EQ(config->num_attention_heads, std::vector<int64_t>(2, UNetConfig::kAttentionHeads));
  EXPECT_EQ(config->reverse_transformer_layers_per_block, (std::vector<int64_t>{3, 1}));
}

// diffusers has no default for text_time's dimensions (its constructor fails without them).
TEST(UNetConfigTest, TextTimeNeedsItsDimensions) {
  auto config = UNetConfig::from_json({{"addition_embed_type", "text_time"}, {"addition_time_embed_dim", 256}});
  ASSERT_FALSE(config.ok());
  EXPECT_TRUE(test::contains_all(std::string(config.status().message()), {"projection_class_embeddings_input_dim"}));
  EXPECT_TRUE(UNetConfig::from_json({{"addition_embed_type", "text_time"},
                                     {"addition_time_embed_dim", 256},
                                     {"projection_class_embeddings_input_dim", 2816}})
                  .ok());
}

TEST(WeightSpecsTest, ListExactlyTheCheckpointsTensors) {
  const ModelFolder f = folder();
  const auto matches = [](const std::vector<TensorSpec>& specs, const TensorMap& checkpoint, const std::string& what) {
    TensorMap weights;  // transformers writes CLIPTextModelWithProjection's tower under "text_model."
    for (const auto& [name, t] : checkpoint)
      weights.emplace(name.rfind("text_model.", 0) == 0 ? name.substr(11) : name, t);
    EXPECT_EQ(specs.size(), weights.size()) << what;
    for (const auto& spec : specs) {
      ASSERT_TRUE(weights.count(spec.name)) << what << ": " << spec.name;
      EXPECT_EQ(weights.at(spec.name).sizes().vec(), spec.shape) << what << ": " << spec.name;
    }
  };
  matches(UNet2DCondition::weight_specs(*UNetConfig::from_json(*f.read_json("unet"))), *f.read_weights("unet"), "unet");
  matches(AutoencoderKL::weight_specs(*VaeConfig::from_json(*f.read_json("vae"))), *f.read_weights("vae"), "vae");
  matches(ClipTextEncoder::weight_specs(*ClipTextConfig::from_json(*f.read_json("text_encoder_2")), true),
          *f.read_weights("text_encoder_2"), "text_encoder_2");
}

TEST(UNet2DConditionTest, ControlResidualsAndAttentionProcessorsChangeTheOutput) {
  const ModelFolder f = folder();
  auto unet = UNet2DCondition::load(*UNetConfig::from_json(*f.read_json("unet")), *f.read_weights("unet"),
                                    at::TensorOptions(), "unet");
  ASSERT_TRUE(unet.ok());
  const TensorMap ref = test::sdxl_reference("unet");
  UNetInputs in{ref.at("sample"), ref.at("timestep"), ref.at("encoder_hidden_states"), ref.at("text_embeds"),
                ref.at("time_ids")};
  const at::Tensor base = unet->forward(in);
  in.mid_block_residual = at::ones({2, 32, 4, 3});
  EXPECT_GT((unet->forward(in) - base).abs().max().item<double>(), 1e-3);
  in.down_block_residuals.assign(3, at::zeros({1}));
  EXPECT_THROW(unet->forward(in), c10::Error);  // wrong count: one per skip connection is required

  // A processor that switches cross-attention off makes the output independent of the text context.
  struct NoContext : AttentionProcessor {
    at::Tensor operator()(const Attention&, const at::Tensor& x, const at::Tensor&) const override {
      return at::zeros_like(x);
    }
  };
  int cross = 0;
  unet->for_each_attention([&](const std::string& name, Attention& a) {
    if (name.size() > 5 && name.substr(name.size() - 5) == "attn2") {
      a.set_processor(std::make_shared<NoContext>());
      ++cross;
    }
  });
  EXPECT_EQ(cross, 2 * 2 + 2 + 3 * 2);  // down block 1: 2 x 2 layers, mid: 2, up block 0: 3 x 2
  in.down_block_residuals.clear();
  in.mid_block_residual = at::Tensor();
  const at::Tensor no_context = unet->forward(in);
  in.encoder_hidden_states = at::randn_like(in.encoder_hidden_states);
  expect_close(unet->forward(in), no_context, 1e-6, "output without context dependence");
}

}  // namespace
}  // namespace gaps::sdxl

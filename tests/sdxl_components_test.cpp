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

#include "diffusion_worker/sdxl/random_model.h"

#include <cmath>
#include <filesystem>
#include <fstream>

#include <ATen/ATen.h>
#include <ATen/CPUGeneratorImpl.h>
#include "absl/strings/str_cat.h"
#include "common/safetensors.h"
#include "common/status_macros.h"
#include "diffusion_worker/sdxl/clip_text_encoder.h"
#include "diffusion_worker/sdxl/unet.h"
#include "diffusion_worker/sdxl/vae.h"

namespace gaps::sdxl {
namespace {

absl::Status write_json(const std::filesystem::path& path, const nlohmann::json& j) {
  std::filesystem::create_directories(path.parent_path());
  std::ofstream out(path);
  out << j.dump(2) << "\n";
  if (!out) return absl::InternalError(absl::StrCat("cannot write ", path.string()));
  return absl::OkStatus();
}

absl::Status write_random_weights(const std::filesystem::path& path, const std::vector<TensorSpec>& specs,
                                  at::Generator& generator, at::ScalarType dtype, const std::string& prefix = "") {
  TensorMap tensors;
  for (const auto& spec : specs) {
    at::Tensor t;
    const bool is_bias = spec.name.size() >= 5 && spec.name.compare(spec.name.size() - 5, 5, ".bias") == 0;
    if (is_bias) {
      t = at::zeros(spec.shape, at::kFloat);
    } else if (spec.shape.size() == 1) {
      t = at::ones(spec.shape, at::kFloat);
    } else if (spec.name.find("embedding.weight") != std::string::npos) {
      t = at::randn(spec.shape, generator, at::kFloat) * 0.02;
    } else {
      int64_t fan_in = 1;
      for (size_t i = 1; i < spec.shape.size(); ++i) fan_in *= spec.shape[i];
      t = at::randn(spec.shape, generator, at::kFloat) / std::sqrt(static_cast<double>(fan_in));
    }
    const bool unprefixed = prefix.empty() || spec.name.rfind("text_projection", 0) == 0;
    tensors.emplace(unprefixed ? spec.name : prefix + spec.name, t.to(dtype));
  }
  std::filesystem::create_directories(path.parent_path());
  return write_safetensors(path.string(), tensors);
}

absl::Status write_tokenizer(const std::filesystem::path& dir, const std::string& pad, int64_t vocab_size) {
  // Byte symbols and their end-of-word forms, unused fillers, then the two specials last (CLIP's ids
  // 49406 and 49407 for its vocabulary of 49408).
  if (vocab_size < 514) return absl::InvalidArgumentError("random SDXL model: vocab_size must be >= 514");
  nlohmann::json vocab = nlohmann::json::object();
  std::vector<std::string> symbols(256);
  uint32_t next = 256;
  const auto utf8 = [](uint32_t cp) {
    std::string s;
    if (cp < 0x80) {
      s += static_cast<char>(cp);
    } else {
      s += static_cast<char>(0xC0 | (cp >> 6));
      s += static_cast<char>(0x80 | (cp & 0x3F));
    }
    return s;
  };
  for (uint32_t b = 0; b < 256; ++b) {
    const bool printable = (b >= '!' && b <= '~') || (b >= 0xA1 && b <= 0xAC) || (b >= 0xAE && b <= 0xFF);
    symbols[b] = utf8(printable ? b : next++);
  }
  int64_t id = 0;
  for (const auto& s : symbols) vocab[s] = id++;
  for (const auto& s : symbols) vocab[s + "</w>"] = id++;
  while (id < vocab_size - 2) {
    vocab[absl::StrCat("<unused", id, ">")] = id;
    ++id;
  }
  vocab["<|startoftext|>"] = vocab_size - 2;
  vocab["<|endoftext|>"] = vocab_size - 1;
  GAPS_RETURN_IF_ERROR(write_json(dir / "vocab.json", vocab));
  std::ofstream(dir / "merges.txt") << "#version: 0.2\n";
  return write_json(dir / "tokenizer_config.json", {{"bos_token", "<|startoftext|>"},
                                                    {"eos_token", "<|endoftext|>"},
                                                    {"unk_token", "<|endoftext|>"},
                                                    {"pad_token", pad},
                                                    {"model_max_length", 77},
                                                    {"tokenizer_class", "CLIPTokenizer"}});
}

}  // namespace

SdxlConfigs SdxlConfigs::base() {
  SdxlConfigs c;
  c.unet = {{"_class_name", "UNet2DConditionModel"},
            {"act_fn", "silu"},
            {"addition_embed_type", "text_time"},
            {"addition_embed_type_num_heads", 64},
            {"addition_time_embed_dim", 256},
            {"attention_head_dim", {5, 10, 20}},
            {"block_out_channels", {320, 640, 1280}},
            {"center_input_sample", false},
            {"class_embed_type", nullptr},
            {"cross_attention_dim", 2048},
            {"down_block_types", {"DownBlock2D", "CrossAttnDownBlock2D", "CrossAttnDownBlock2D"}},
            {"downsample_padding", 1},
            {"flip_sin_to_cos", true},
            {"freq_shift", 0},
            {"in_channels", 4},
            {"layers_per_block", 2},
            {"mid_block_type", "UNetMidBlock2DCrossAttn"},
            {"norm_eps", 1e-5},
            {"norm_num_groups", 32},
            {"out_channels", 4},
            {"projection_class_embeddings_input_dim", 2816},
            {"resnet_time_scale_shift", "default"},
            {"sample_size", 128},
            {"time_embedding_type", "positional"},
            {"transformer_layers_per_block", {1, 2, 10}},
            {"up_block_types", {"CrossAttnUpBlock2D", "CrossAttnUpBlock2D", "UpBlock2D"}},
            {"upcast_attention", nullptr},
            {"use_linear_projection", true}};
  c.vae = {{"_class_name", "AutoencoderKL"},
           {"act_fn", "silu"},
           {"block_out_channels", {128, 256, 512, 512}},
           {"down_block_types", std::vector<std::string>(4, "DownEncoderBlock2D")},
           {"up_block_types", std::vector<std::string>(4, "UpDecoderBlock2D")},
           {"force_upcast", true},
           {"in_channels", 3},
           {"out_channels", 3},
           {"latent_channels", 4},
           {"layers_per_block", 2},
           {"norm_num_groups", 32},
           {"sample_size", 1024},
           {"scaling_factor", 0.13025}};
  for (bool second : {false, true}) {
    (second ? c.text_encoder_2 : c.text_encoder) = {
        {"architectures", {second ? "CLIPTextModelWithProjection" : "CLIPTextModel"}},
        {"model_type", "clip_text_model"},
        {"attention_dropout", 0.0},
        {"bos_token_id", 0},
        {"eos_token_id", 2},
        {"pad_token_id", 1},
        {"hidden_act", second ? "gelu" : "quick_gelu"},
        {"hidden_size", second ? 1280 : 768},
        {"intermediate_size", second ? 5120 : 3072},
        {"initializer_factor", 1.0},
        {"initializer_range", 0.02},
        {"layer_norm_eps", 1e-5},
        {"max_position_embeddings", 77},
        {"num_attention_heads", second ? 20 : 12},
        {"num_hidden_layers", second ? 32 : 12},
        {"projection_dim", second ? 1280 : 768},
        {"vocab_size", 49408},
        {"torch_dtype", "float16"}};
  }
  c.scheduler = {{"_class_name", "EulerDiscreteScheduler"},
                 {"beta_end", 0.012},
                 {"beta_schedule", "scaled_linear"},
                 {"beta_start", 0.00085},
                 {"clip_sample", false},
                 {"interpolation_type", "linear"},
                 {"num_train_timesteps", 1000},
                 {"prediction_type", "epsilon"},
                 {"sample_max_value", 1.0},
                 {"set_alpha_to_one", false},
                 {"skip_prk_steps", true},
                 {"steps_offset", 1},
                 {"timestep_spacing", "leading"},
                 {"trained_betas", nullptr},
                 {"use_karras_sigmas", false}};
  return c;
}

absl::Status write_random_sdxl_model(const std::string& folder, const SdxlConfigs& configs, uint64_t seed,
                                     const std::string& dtype_name) {
  at::ScalarType dtype;
  if (dtype_name == "float16") {
    dtype = at::kHalf;
  } else if (dtype_name == "bfloat16") {
    dtype = at::kBFloat16;
  } else if (dtype_name == "float32") {
    dtype = at::kFloat;
  } else {
    return absl::InvalidArgumentError(absl::StrCat("random SDXL model: unknown dtype ", dtype_name));
  }
  const std::filesystem::path root(folder);
  GAPS_RETURN_IF_ERROR(
      write_json(root / "model_index.json", {{"_class_name", "StableDiffusionXLImg2ImgPipeline"},
                                             {"force_zeros_for_empty_prompt", true},
                                             {"requires_aesthetics_score", false},
                                             {"scheduler", {"diffusers", "EulerDiscreteScheduler"}},
                                             {"text_encoder", {"transformers", "CLIPTextModel"}},
                                             {"text_encoder_2", {"transformers", "CLIPTextModelWithProjection"}},
                                             {"tokenizer", {"transformers", "CLIPTokenizer"}},
                                             {"tokenizer_2", {"transformers", "CLIPTokenizer"}},
                                             {"unet", {"diffusers", "UNet2DConditionModel"}},
                                             {"vae", {"diffusers", "AutoencoderKL"}}}));
  GAPS_RETURN_IF_ERROR(write_json(root / "scheduler" / "scheduler_config.json", configs.scheduler));
  GAPS_RETURN_IF_ERROR(
      write_tokenizer(root / "tokenizer", "<|endoftext|>", configs.text_encoder.value("vocab_size", 49408)));
  GAPS_RETURN_IF_ERROR(write_tokenizer(root / "tokenizer_2", "!", configs.text_encoder_2.value("vocab_size", 49408)));

  at::Generator generator = at::make_generator<at::CPUGeneratorImpl>(seed);
  const nlohmann::json& unet_json = configs.unet;
  const nlohmann::json& vae_json = configs.vae;
  GAPS_ASSIGN_OR_RETURN(UNetConfig unet, UNetConfig::from_json(unet_json));
  GAPS_ASSIGN_OR_RETURN(VaeConfig vae, VaeConfig::from_json(vae_json));
  GAPS_RETURN_IF_ERROR(write_json(root / "unet" / "config.json", unet_json));
  GAPS_RETURN_IF_ERROR(write_random_weights(root / "unet" / "diffusion_pytorch_model.safetensors",
                                            UNet2DCondition::weight_specs(unet), generator, dtype));
  GAPS_RETURN_IF_ERROR(write_json(root / "vae" / "config.json", vae_json));
  GAPS_RETURN_IF_ERROR(write_random_weights(root / "vae" / "diffusion_pytorch_model.safetensors",
                                            AutoencoderKL::weight_specs(vae), generator, dtype));
  for (bool second : {false, true}) {
    const nlohmann::json& json = second ? configs.text_encoder_2 : configs.text_encoder;
    GAPS_ASSIGN_OR_RETURN(ClipTextConfig config, ClipTextConfig::from_json(json));
    const std::filesystem::path dir = root / (second ? "text_encoder_2" : "text_encoder");
    GAPS_RETURN_IF_ERROR(write_json(dir / "config.json", json));
    GAPS_RETURN_IF_ERROR(write_random_weights(dir / "model.safetensors", ClipTextEncoder::weight_specs(config, second),
                                              generator, dtype, "text_model."));
  }
  return absl::OkStatus();
}

}  // namespace gaps::sdxl

#include "diffusion_worker/sdxl/pipeline.h"

#include <utility>

#include <ATen/ATen.h>
#include <ATen/CPUGeneratorImpl.h>
#include "absl/strings/str_cat.h"
#include "diffusion_worker/sdxl/model_folder.h"
#include "gs_trainer/status_macros.h"

namespace gaps::sdxl {
namespace {

absl::Status in_component(const std::string& component, const absl::Status& status) {
  if (status.ok()) return status;
  return absl::Status(status.code(), absl::StrCat("SDXL component '", component, "': ", status.message()));
}

absl::Status expect_class(const ModelFolder& folder, const std::string& component, const std::string& expected) {
  GAPS_ASSIGN_OR_RETURN(std::string cls, folder.component_class(component));
  if (cls != expected) {
    return absl::InvalidArgumentError(absl::StrCat(folder.root(), ": component '", component, "' is ", cls,
                                                   ", an SDXL pipeline needs ", expected));
  }
  return absl::OkStatus();
}

at::Tensor token_tensor(const ClipTokenizer& tok, const std::vector<std::string>& prompts) {
  std::vector<int64_t> ids;
  for (const auto& p : prompts) {
    const auto one = tok.encode(p, tok.model_max_length());
    ids.insert(ids.end(), one.begin(), one.end());
  }
  return at::tensor(ids, at::kLong).view({static_cast<int64_t>(prompts.size()), -1});
}

}  // namespace

absl::StatusOr<std::unique_ptr<SdxlPipeline>> SdxlPipeline::load(const std::string& root, const PipelineOptions& options) {
  GAPS_ASSIGN_OR_RETURN(ModelFolder folder, ModelFolder::open(root));
  for (const auto& [component, cls] : std::vector<std::pair<std::string, std::string>>{
           {"unet", "UNet2DConditionModel"}, {"vae", "AutoencoderKL"}, {"text_encoder", "CLIPTextModel"},
           {"text_encoder_2", "CLIPTextModelWithProjection"}, {"tokenizer", "CLIPTokenizer"},
           {"tokenizer_2", "CLIPTokenizer"}}) {
    GAPS_RETURN_IF_ERROR(expect_class(folder, component, cls));
  }
  auto p = std::make_unique<SdxlPipeline>();
  p->options_ = options;
  if (folder.index().contains("force_zeros_for_empty_prompt")) {
    p->force_zeros_for_empty_prompt_ = folder.index()["force_zeros_for_empty_prompt"].get<bool>();
  }
  const at::TensorOptions model_options = at::TensorOptions().dtype(options.dtype).device(options.device);

  GAPS_ASSIGN_OR_RETURN(auto scheduler_json, folder.read_json("scheduler", "scheduler_config.json"));
  GAPS_ASSIGN_OR_RETURN(p->scheduler_config_, SchedulerConfig::from_json(scheduler_json, options.scheduler));

  for (const char* name : {"tokenizer", "tokenizer_2"}) {
    auto tok = ClipTokenizer::load(folder.component_dir(name));
    GAPS_RETURN_IF_ERROR(in_component(name, tok.status()));
    (std::string(name) == "tokenizer" ? p->tokenizer_ : p->tokenizer_2_) = *std::move(tok);
  }
  for (const char* name : {"text_encoder", "text_encoder_2"}) {
    const bool projection = std::string(name) == "text_encoder_2";
    auto json = folder.read_json(name);
    GAPS_RETURN_IF_ERROR(in_component(name, json.status()));
    auto config = ClipTextConfig::from_json(*json);
    GAPS_RETURN_IF_ERROR(in_component(name, config.status()));
    auto weights = folder.read_weights(name);
    GAPS_RETURN_IF_ERROR(in_component(name, weights.status()));
    auto encoder = ClipTextEncoder::load(*config, projection, *std::move(weights), model_options, folder.component_dir(name));
    GAPS_RETURN_IF_ERROR(in_component(name, encoder.status()));
    (projection ? p->text_encoder_2_ : p->text_encoder_) = *std::move(encoder);
  }
  {
    auto json = folder.read_json("unet");
    GAPS_RETURN_IF_ERROR(in_component("unet", json.status()));
    auto config = UNetConfig::from_json(*json);
    GAPS_RETURN_IF_ERROR(in_component("unet", config.status()));
    const int64_t text_dim = p->text_encoder_->config().hidden_size + p->text_encoder_2_->config().hidden_size;
    if (config->cross_attention_dim != text_dim || config->addition_embed_type != "text_time" ||
        config->projection_class_embeddings_input_dim !=
            6 * config->addition_time_embed_dim + p->text_encoder_2_->config().projection_dim) {
      return absl::InvalidArgumentError(absl::StrCat(
          root, ": the UNet is not an SDXL base UNet for these text encoders (needs cross_attention_dim ", text_dim,
          ", addition_embed_type text_time and projection_class_embeddings_input_dim 6 x addition_time_embed_dim + ",
          p->text_encoder_2_->config().projection_dim, ")"));
    }
    auto weights = folder.read_weights("unet");
    GAPS_RETURN_IF_ERROR(in_component("unet", weights.status()));
    auto unet = UNet2DCondition::load(*config, *std::move(weights), model_options, folder.component_dir("unet"));
    GAPS_RETURN_IF_ERROR(in_component("unet", unet.status()));
    p->unet_ = *std::move(unet);
  }
  {
    auto json = folder.read_json("vae");
    GAPS_RETURN_IF_ERROR(in_component("vae", json.status()));
    auto config = VaeConfig::from_json(*json);
    GAPS_RETURN_IF_ERROR(in_component("vae", config.status()));
    const bool upcast = json->value("force_upcast", true);
    auto weights = folder.read_weights("vae");
    GAPS_RETURN_IF_ERROR(in_component("vae", weights.status()));
    auto vae = AutoencoderKL::load(*config, *std::move(weights), upcast ? model_options.dtype(at::kFloat) : model_options,
                                   folder.component_dir("vae"));
    GAPS_RETURN_IF_ERROR(in_component("vae", vae.status()));
    p->vae_ = *std::move(vae);
  }
  return p;
}

PromptEmbeddings SdxlPipeline::encode_prompts(const std::vector<std::string>& prompts) const {
  const ClipTextOutput one = text_encoder_->forward(token_tensor(*tokenizer_, prompts));
  const ClipTextOutput two = text_encoder_2_->forward(token_tensor(*tokenizer_2_, prompts));
  return {at::cat({one.penultimate, two.penultimate}, -1), two.text_embeds};
}

absl::StatusOr<at::Tensor> SdxlPipeline::img2img(const at::Tensor& images, const std::vector<std::string>& prompts,
                                                 const Img2ImgParams& params, const std::vector<uint64_t>& seeds) {
  const int64_t batch = images.size(0), height = images.size(2), width = images.size(3), f = latent_factor();
  if (images.dim() != 4 || images.size(1) != 3) return absl::InvalidArgumentError("img2img: images must be B x 3 x H x W");
  if (height % f != 0 || width % f != 0) {
    return absl::InvalidArgumentError(absl::StrCat("img2img: image size ", height, "x", width, " is not a multiple of ", f));
  }
  if (prompts.size() != 1 && static_cast<int64_t>(prompts.size()) != batch) {
    return absl::InvalidArgumentError("img2img: give one prompt, or one per image");
  }
  if (seeds.size() != 1 && static_cast<int64_t>(seeds.size()) != batch) {
    return absl::InvalidArgumentError("img2img: give one seed, or one per image");
  }
  if (!(params.strength > 0 && params.strength <= 1) || params.steps < 1) {
    return absl::InvalidArgumentError("img2img: strength must be in (0, 1] and steps >= 1");
  }
  GAPS_ASSIGN_OR_RETURN(std::unique_ptr<Scheduler> scheduler, make_scheduler(scheduler_config_));
  scheduler->set_timesteps(params.steps);
  const int64_t init_steps = std::min<int64_t>(static_cast<int64_t>(params.steps * params.strength), params.steps);
  const int64_t start = params.steps - init_steps;
  if (init_steps < 1) {
    return absl::InvalidArgumentError(absl::StrCat("img2img: strength ", params.strength, " with ", params.steps,
                                                   " steps leaves no step to run"));
  }

  const std::vector<std::string> all_prompts = prompts.size() == 1 ? std::vector<std::string>(batch, prompts[0]) : prompts;
  const bool cfg = params.guidance_scale > 1.0;
  PromptEmbeddings cond = encode_prompts(all_prompts);
  at::Tensor context = cond.context, pooled = cond.pooled;
  if (cfg) {
    PromptEmbeddings uncond = force_zeros_for_empty_prompt_
                                  ? PromptEmbeddings{at::zeros_like(cond.context), at::zeros_like(cond.pooled)}
                                  : encode_prompts(std::vector<std::string>(batch, ""));
    context = at::cat({uncond.context, cond.context});
    pooled = at::cat({uncond.pooled, cond.pooled});
  }
  const at::Tensor time_ids = at::tensor(std::vector<float>{static_cast<float>(height), static_cast<float>(width), 0.0f,
                                                            0.0f, static_cast<float>(height), static_cast<float>(width)})
                                  .view({1, 6})
                                  .expand({context.size(0), 6})
                                  .contiguous();

  // Random draws on the CPU in float32 (diffusers' randn_tensor with CPU generators): per generator,
  // first the latent-distribution sample, then the noise.
  const at::Tensor moments = vae_->encode_moments((images.to(options_.device, at::kFloat) * 2 - 1).to(vae_->dtype()));
  std::vector<at::Generator> generators;
  for (uint64_t seed : seeds) generators.push_back(at::make_generator<at::CPUGeneratorImpl>(seed));
  const auto parts = moments.chunk(2, 1);
  const at::Tensor mean = parts[0].to(at::kCPU, at::kFloat);
  const at::Tensor std = at::exp(0.5 * at::clamp(parts[1].to(at::kCPU, at::kFloat), -30.0, 20.0));
  at::Tensor latent_noise, noise;
  if (generators.size() == 1) {
    latent_noise = at::randn(mean.sizes(), generators[0], at::kFloat);
    noise = at::randn(mean.sizes(), generators[0], at::kFloat);
  } else {
    std::vector<at::Tensor> a, b;
    for (int64_t i = 0; i < batch; ++i) {
      a.push_back(at::randn({1, mean.size(1), mean.size(2), mean.size(3)}, generators[i], at::kFloat));
      b.push_back(at::randn({1, mean.size(1), mean.size(2), mean.size(3)}, generators[i], at::kFloat));
    }
    latent_noise = at::cat(a);
    noise = at::cat(b);
  }
  const double scaling = vae_->config().scaling_factor;
  at::Tensor latents = (mean + std * latent_noise) * scaling;
  latents = scheduler->add_noise(latents, noise, start).to(options_.device, options_.dtype);

  UNetInputs in;
  in.encoder_hidden_states = context;
  in.text_embeds = pooled;
  in.time_ids = time_ids.to(options_.device);
  for (int64_t i = start; i < params.steps; ++i) {
    const at::Tensor model_input = cfg ? at::cat({latents, latents}) : latents;
    in.sample = scheduler->scale_model_input(model_input, i);
    in.timestep = at::scalar_tensor(scheduler->timesteps()[i], at::TensorOptions().device(options_.device));
    at::Tensor prediction = unet_->forward(in);
    if (cfg) prediction = classifier_free_guidance(prediction, params.guidance_scale);
    latents = scheduler->step(prediction, i, latents);
  }
  const at::Tensor decoded = vae_->decode((latents / scaling).to(vae_->dtype()));
  return (decoded.to(at::kCPU, at::kFloat) / 2 + 0.5).clamp(0, 1);
}

}  // namespace gaps::sdxl

#include "diffusion_worker/sdxl/inpaint_pipeline.h"

#include <algorithm>
#include <utility>

#include <ATen/ATen.h>
#include <ATen/CPUGeneratorImpl.h>
#include <c10/core/InferenceMode.h>
#include "absl/strings/str_cat.h"
#include "common/status_macros.h"
#include "diffusion_worker/sdxl/model_folder.h"

namespace gaps::sdxl {
namespace {

template <typename T>
absl::StatusOr<T> in_component(const std::string& component, absl::StatusOr<T> value) {
  if (value.ok()) return value;
  return absl::Status(value.status().code(),
                      absl::StrCat("inpainting component '", component, "': ", value.status().message()));
}

absl::Status expect_class(const ModelFolder& folder, const std::string& component, const std::string& expected) {
  GAPS_ASSIGN_OR_RETURN(std::string cls, folder.component_class(component));
  if (cls != expected) {
    return absl::InvalidArgumentError(absl::StrCat(folder.root(), ": component '", component, "' is ", cls,
                                                   ", an inpainting pipeline needs ", expected));
  }
  return absl::OkStatus();
}

// diffusers' generator semantics: one generator draws for the whole batch; a list draws image by image.
class SeededDraws {
 public:
  explicit SeededDraws(const std::vector<uint64_t>& seeds) {
    for (uint64_t seed : seeds) generators_.push_back(at::make_generator<at::CPUGeneratorImpl>(seed));
  }
  // N(0, 1) in float32 on the CPU, shape B x ...
  at::Tensor randn(at::IntArrayRef shape) {
    if (generators_.size() == 1) return at::randn(shape, generators_[0], at::kFloat);
    std::vector<int64_t> one = shape.vec();
    one[0] = 1;
    std::vector<at::Tensor> parts;
    for (at::Generator& g : generators_) parts.push_back(at::randn(one, g, at::kFloat));
    return at::cat(parts);
  }
  // A draw from the VAE's latent distribution given its moments, B x L x h x w.
  at::Tensor sample_latents(const AutoencoderKL& vae, const at::Tensor& moments) {
    if (generators_.size() == 1) return vae.sample_latents(moments, generators_[0]);
    std::vector<at::Tensor> parts;
    for (size_t i = 0; i < generators_.size(); ++i) {
      parts.push_back(vae.sample_latents(moments.slice(0, i, i + 1), generators_[i]));
    }
    return at::cat(parts);
  }

 private:
  std::vector<at::Generator> generators_;
};

std::vector<std::string> per_image(const std::vector<std::string>& texts, int64_t batch, const std::string& fallback) {
  if (texts.empty()) return std::vector<std::string>(batch, fallback);
  if (texts.size() == 1) return std::vector<std::string>(batch, texts[0]);
  return texts;
}

}  // namespace

absl::StatusOr<std::unique_ptr<InpaintPipeline>> InpaintPipeline::load(const std::string& root,
                                                                       const InpaintPipelineOptions& options) {
  GAPS_ASSIGN_OR_RETURN(ModelFolder folder, ModelFolder::open(root));
  for (const auto& [component, cls] :
       std::vector<std::pair<std::string, std::string>>{{"unet", "UNet2DConditionModel"},
                                                        {"vae", "AutoencoderKL"},
                                                        {"text_encoder", "CLIPTextModel"},
                                                        {"tokenizer", "CLIPTokenizer"}}) {
    GAPS_RETURN_IF_ERROR(expect_class(folder, component, cls));
  }
  auto p = std::make_unique<InpaintPipeline>();
  p->options_ = options;
  const at::TensorOptions model_options = at::TensorOptions().dtype(options.dtype).device(options.device);

  GAPS_ASSIGN_OR_RETURN(auto scheduler_json,
                        in_component("scheduler", folder.read_json("scheduler", "scheduler_config.json")));
  GAPS_ASSIGN_OR_RETURN(p->scheduler_config_,
                        in_component("scheduler", SchedulerConfig::from_json(scheduler_json, options.scheduler)));
  GAPS_ASSIGN_OR_RETURN(p->tokenizer_,
                        in_component("tokenizer", ClipTokenizer::load(folder.component_dir("tokenizer"))));

  GAPS_ASSIGN_OR_RETURN(auto text_json, in_component("text_encoder", folder.read_json("text_encoder")));
  GAPS_ASSIGN_OR_RETURN(auto text_config, in_component("text_encoder", ClipTextConfig::from_json(text_json)));
  GAPS_ASSIGN_OR_RETURN(auto text_weights,
                        in_component("text_encoder", folder.read_weights("text_encoder", options.variant)));
  GAPS_ASSIGN_OR_RETURN(
      p->text_encoder_,
      in_component("text_encoder", ClipTextEncoder::load(text_config, false, std::move(text_weights), model_options,
                                                         folder.component_dir("text_encoder"))));

  GAPS_ASSIGN_OR_RETURN(auto vae_json, in_component("vae", folder.read_json("vae")));
  GAPS_ASSIGN_OR_RETURN(auto vae_config, in_component("vae", VaeConfig::from_json(vae_json)));
  GAPS_ASSIGN_OR_RETURN(auto vae_weights, in_component("vae", folder.read_weights("vae", options.variant)));
  const bool upcast = vae_json.value("force_upcast", true);
  GAPS_ASSIGN_OR_RETURN(
      p->vae_, in_component("vae", AutoencoderKL::load(vae_config, std::move(vae_weights),
                                                       upcast ? model_options.dtype(at::kFloat) : model_options,
                                                       folder.component_dir("vae"))));

  GAPS_ASSIGN_OR_RETURN(auto unet_json, in_component("unet", folder.read_json("unet")));
  GAPS_ASSIGN_OR_RETURN(auto unet_config, in_component("unet", UNetConfig::from_json(unet_json)));
  const int64_t latent_channels = vae_config.latent_channels;
  if (unet_config.in_channels != 2 * latent_channels + 1 || unet_config.out_channels != latent_channels ||
      unet_config.cross_attention_dim != text_config.hidden_size || !unet_config.addition_embed_type.empty()) {
    return absl::InvalidArgumentError(
        absl::StrCat(root, ": the UNet is not an inpainting UNet for this VAE and text encoder (needs in_channels ",
                     2 * latent_channels + 1, " = latents, mask and masked-image latents; out_channels ",
                     latent_channels, "; cross_attention_dim ", text_config.hidden_size,
                     "; no addition_embed_type); it has in_channels ", unet_config.in_channels, ", out_channels ",
                     unet_config.out_channels, ", cross_attention_dim ", unet_config.cross_attention_dim));
  }
  GAPS_ASSIGN_OR_RETURN(auto unet_weights, in_component("unet", folder.read_weights("unet", options.variant)));
  GAPS_ASSIGN_OR_RETURN(p->unet_,
                        in_component("unet", UNet2DCondition::load(unet_config, std::move(unet_weights), model_options,
                                                                   folder.component_dir("unet"))));
  return p;
}

at::Tensor InpaintPipeline::encode_prompts(const std::vector<std::string>& prompts) const {
  std::vector<int64_t> ids;
  for (const auto& prompt : prompts) {
    const auto one = tokenizer_->encode(prompt, tokenizer_->model_max_length());
    ids.insert(ids.end(), one.begin(), one.end());
  }
  const at::Tensor tokens = at::tensor(ids, at::kLong).view({static_cast<int64_t>(prompts.size()), -1});
  return text_encoder_->forward(tokens).last_hidden_state;
}

at::Tensor InpaintPipeline::prompt_context(const std::vector<std::string>& prompts, const InpaintParams& params,
                                           int64_t batch) const {
  const at::Tensor cond = encode_prompts(per_image(prompts, batch, ""));
  if (params.guidance_scale <= 1.0) return cond;
  return at::cat({encode_prompts(per_image(params.negative_prompts, batch, "")), cond});
}

absl::Status InpaintPipeline::check_inputs(const at::Tensor& images, const at::Tensor& masks,
                                           const std::vector<std::string>& prompts, const InpaintParams& params,
                                           const std::vector<uint64_t>& seeds) const {
  if (!images.defined() || images.dim() != 4 || images.size(1) != 3) {
    return absl::InvalidArgumentError("inpaint: images must be B x 3 x H x W");
  }
  const int64_t batch = images.size(0), height = images.size(2), width = images.size(3), f = latent_factor();
  if (!masks.defined() || masks.dim() != 4 || masks.size(0) != batch || masks.size(1) != 1 || masks.size(2) != height ||
      masks.size(3) != width) {
    return absl::InvalidArgumentError(absl::StrCat("inpaint: masks must be B x 1 x H x W like the images (", batch,
                                                   " x 1 x ", height, " x ", width, ")"));
  }
  if (height % f != 0 || width % f != 0) {
    return absl::InvalidArgumentError(
        absl::StrCat("inpaint: image size ", height, "x", width, " is not a multiple of ", f));
  }
  const auto one_or_batch = [batch](size_t n) { return n == 1 || static_cast<int64_t>(n) == batch; };
  if (!one_or_batch(prompts.size())) return absl::InvalidArgumentError("inpaint: give one prompt, or one per image");
  if (!params.negative_prompts.empty() && !one_or_batch(params.negative_prompts.size())) {
    return absl::InvalidArgumentError("inpaint: give no negative prompt, one, or one per image");
  }
  if (!one_or_batch(seeds.size())) return absl::InvalidArgumentError("inpaint: give one seed, or one per image");
  if (!(params.strength > 0 && params.strength <= 1) || params.steps < 1) {
    return absl::InvalidArgumentError("inpaint: strength must be in (0, 1] and steps >= 1");
  }
  if (static_cast<int64_t>(params.steps * params.strength) < 1) {
    return absl::InvalidArgumentError(
        absl::StrCat("inpaint: strength ", params.strength, " with ", params.steps, " steps leaves no step to run"));
  }
  return absl::OkStatus();
}

absl::StatusOr<at::Tensor> InpaintPipeline::inpaint(const at::Tensor& images, const at::Tensor& masks,
                                                    const std::vector<std::string>& prompts,
                                                    const InpaintParams& params, const std::vector<uint64_t>& seeds) {
  GAPS_RETURN_IF_ERROR(check_inputs(images, masks, prompts, params, seeds));
  const int64_t batch = images.size(0), f = latent_factor();
  GAPS_ASSIGN_OR_RETURN(std::unique_ptr<Scheduler> scheduler, make_scheduler(scheduler_config_));
  scheduler->set_timesteps(params.steps);
  // diffusers' get_timesteps: the last int(steps * strength) steps of the schedule.
  const int64_t run_steps = std::min<int64_t>(static_cast<int64_t>(params.steps * params.strength), params.steps);
  const int64_t start = params.steps - run_steps;
  const bool from_noise = params.strength == 1.0;
  const bool cfg = params.guidance_scale > 1.0;
  const at::TensorOptions model_options = at::TensorOptions().dtype(options_.dtype).device(options_.device);
  at::Tensor result;
  {
    c10::InferenceMode inference;
    const at::Tensor mask = (masks.to(at::kFloat) >= 0.5).to(at::kFloat);
    const at::Tensor image = images.to(at::kFloat) * 2 - 1;
    const at::Tensor masked_image = image * (mask < 0.5);
    const auto moments = [&](const at::Tensor& x) {
      return vae_->encode_moments(x.to(options_.device, vae_->dtype()));
    };
    const double scaling = vae_->config().scaling_factor;
    // The draws in diffusers' order: image latents (strength < 1 only), noise, masked-image latents.
    SeededDraws draws(seeds);
    at::Tensor image_latents;
    if (!from_noise) image_latents = draws.sample_latents(*vae_, moments(image)).to(at::kCPU, at::kFloat) * scaling;
    const int64_t lh = images.size(2) / f, lw = images.size(3) / f;
    const at::Tensor noise = draws.randn({batch, vae_->config().latent_channels, lh, lw});
    at::Tensor latents =
        from_noise ? noise * scheduler->init_noise_sigma() : scheduler->add_noise(image_latents, noise, start);
    const at::Tensor masked_latents = draws.sample_latents(*vae_, moments(masked_image)).to(model_options) * scaling;
    const at::Tensor latent_mask = at::upsample_nearest2d(mask, {lh, lw}).to(model_options);

    const at::Tensor context = prompt_context(prompts, params, batch);
    const at::Tensor conditioning =
        cfg ? at::cat({at::cat({latent_mask, masked_latents}, 1), at::cat({latent_mask, masked_latents}, 1)})
            : at::cat({latent_mask, masked_latents}, 1);
    latents = latents.to(model_options);
    UNetInputs in;
    in.encoder_hidden_states = context;
    const auto steps = static_cast<int64_t>(scheduler->timesteps().size());
    for (int64_t i = start; i < steps; ++i) {
      const at::Tensor scaled = scheduler->scale_model_input(cfg ? at::cat({latents, latents}) : latents, i);
      in.sample = at::cat({scaled, conditioning}, 1);
      in.timestep = at::scalar_tensor(scheduler->timesteps()[i], at::TensorOptions().device(options_.device));
      at::Tensor prediction = unet_->forward(in);
      if (cfg) prediction = classifier_free_guidance(prediction, params.guidance_scale);
      latents = scheduler->step(prediction, i, latents);
    }
    const at::Tensor decoded = vae_->decode((latents / scaling).to(vae_->dtype()));
    result = (decoded.to(at::kCPU, at::kFloat) / 2 + 0.5).clamp(0, 1);
  }
  return result.clone();
}

}  // namespace gaps::sdxl

#include "diffusion_worker/sdxl/pipeline.h"

#include <algorithm>
#include <cmath>
#include <map>
#include <optional>
#include <utility>
#include <vector>

#include <ATen/ATen.h>
#include <ATen/CPUGeneratorImpl.h>
#include <ATen/core/grad_mode.h>
#include <c10/core/InferenceMode.h>
#include "absl/strings/str_cat.h"
#include "common/status_macros.h"
#include "diffusion_worker/sdxl/model_folder.h"

#if defined(GAPS_CUDA_KERNELS)
#include <ATen/cuda/CUDAGraph.h>
#include "diffusion_worker/sdxl/side_stream.h"
#endif

namespace gaps::sdxl {

#if defined(GAPS_CUDA_KERNELS)
// One captured UNet forward per input shape, with the static input and output buffers it reads and
// writes; a step copies its inputs into the buffers and replays.
struct UNetGraphs {
  struct Entry {
    at::cuda::CUDAGraph graph;
    UNetInputs inputs;
    at::Tensor output;
  };
  std::map<std::vector<int64_t>, std::unique_ptr<Entry>> entries;
  // Graphs never run concurrently, so they share one memory pool (the first graph's).
  std::optional<at::cuda::MempoolId_t> pool;

  at::Tensor run(const UNet2DCondition& unet, const UNetInputs& in) {
    std::vector<int64_t> key = in.sample.sizes().vec();
    for (int64_t d : in.encoder_hidden_states.sizes()) key.push_back(d);
    key.push_back(static_cast<int64_t>(in.down_block_residuals.size()));  // with or without ControlNet
    auto it = entries.find(key);
    if (it == entries.end()) {
      auto entry = std::make_unique<Entry>();
      entry->inputs = in;
      for (at::Tensor* t : {&entry->inputs.sample, &entry->inputs.timestep, &entry->inputs.encoder_hidden_states,
                            &entry->inputs.text_embeds, &entry->inputs.time_ids}) {
        *t = t->clone();
      }
      for (at::Tensor& r : entry->inputs.down_block_residuals) r = r.clone();
      if (in.mid_block_residual.defined()) entry->inputs.mid_block_residual = in.mid_block_residual.clone();
      {
        const SideStream capture_stream(in.sample.device().index());
        for (int i = 0; i < 2; ++i) entry->output = unet.forward(entry->inputs);  // warm-up before capture
        // Thread-local capture: other threads (the trainer) may keep using the GPU meanwhile.
        entry->graph.capture_begin(pool.value_or(at::cuda::MempoolId_t{0, 0}), cudaStreamCaptureModeThreadLocal);
        entry->output = unet.forward(entry->inputs);
        entry->graph.capture_end();
        if (!pool) pool = entry->graph.pool();
      }
      it = entries.emplace(key, std::move(entry)).first;
    }
    Entry& e = *it->second;
    e.inputs.sample.copy_(in.sample);
    e.inputs.timestep.copy_(in.timestep);
    e.inputs.encoder_hidden_states.copy_(in.encoder_hidden_states);
    e.inputs.text_embeds.copy_(in.text_embeds);
    e.inputs.time_ids.copy_(in.time_ids);
    for (size_t i = 0; i < in.down_block_residuals.size(); ++i)
      e.inputs.down_block_residuals[i].copy_(in.down_block_residuals[i]);
    if (in.mid_block_residual.defined()) e.inputs.mid_block_residual.copy_(in.mid_block_residual);
    e.graph.replay();
    return e.output.clone();
  }
};
#else
struct UNetGraphs {};
#endif

namespace {

absl::Status in_component(const std::string& component, const absl::Status& status) {
  if (status.ok()) return status;
  return absl::Status(status.code(), absl::StrCat("SDXL component '", component, "': ", status.message()));
}

absl::Status expect_class(const ModelFolder& folder, const std::string& component, const std::string& expected) {
  GAPS_ASSIGN_OR_RETURN(std::string cls, folder.component_class(component));
  if (cls != expected) {
    return absl::InvalidArgumentError(
        absl::StrCat(folder.root(), ": component '", component, "' is ", cls, ", an SDXL pipeline needs ", expected));
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

absl::StatusOr<std::unique_ptr<SdxlPipeline>> SdxlPipeline::load(const std::string& root,
                                                                 const PipelineOptions& options) {
  GAPS_ASSIGN_OR_RETURN(ModelFolder folder, ModelFolder::open(root));
  for (const auto& [component, cls] :
       std::vector<std::pair<std::string, std::string>>{{"unet", "UNet2DConditionModel"},
                                                        {"vae", "AutoencoderKL"},
                                                        {"text_encoder", "CLIPTextModel"},
                                                        {"text_encoder_2", "CLIPTextModelWithProjection"},
                                                        {"tokenizer", "CLIPTokenizer"},
                                                        {"tokenizer_2", "CLIPTokenizer"}}) {
    GAPS_RETURN_IF_ERROR(expect_class(folder, component, cls));
  }
  auto p = std::make_unique<SdxlPipeline>();
  p->options_ = options;
  GAPS_RETURN_IF_ERROR(p->set_cuda_graphs(options.cuda_graphs));
  if (folder.index().value("requires_aesthetics_score", false)) {
    return absl::UnimplementedError(
        absl::StrCat(root, ": aesthetic-score conditioning (the SDXL refiner) is not supported"));
  }
  if (folder.index().contains("force_zeros_for_empty_prompt")) {
    p->force_zeros_for_empty_prompt_ = folder.index()["force_zeros_for_empty_prompt"].get<bool>();
  }
  const at::TensorOptions model_options = at::TensorOptions().dtype(options.dtype).device(options.device);
  const at::TensorOptions conv_options = p->convolution_options();

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
    auto weights = folder.read_weights(name, options.variant);
    GAPS_RETURN_IF_ERROR(in_component(name, weights.status()));
    auto encoder =
        ClipTextEncoder::load(*config, projection, *std::move(weights), model_options, folder.component_dir(name));
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
    auto weights = folder.read_weights("unet", options.variant);
    GAPS_RETURN_IF_ERROR(in_component("unet", weights.status()));
    auto unet = UNet2DCondition::load(*config, *std::move(weights), conv_options, folder.component_dir("unet"));
    GAPS_RETURN_IF_ERROR(in_component("unet", unet.status()));
    p->unet_ = *std::move(unet);
  }
  {
    auto json = folder.read_json("vae");
    GAPS_RETURN_IF_ERROR(in_component("vae", json.status()));
    auto config = VaeConfig::from_json(*json);
    GAPS_RETURN_IF_ERROR(in_component("vae", config.status()));
    const bool upcast = json->value("force_upcast", true);
    auto weights = folder.read_weights("vae", options.variant);
    GAPS_RETURN_IF_ERROR(in_component("vae", weights.status()));
    const at::ScalarType vae_dtype = options.vae_dtype.value_or(upcast ? at::kFloat : options.dtype);
    auto vae =
        AutoencoderKL::load(*config, *std::move(weights), conv_options.dtype(vae_dtype), folder.component_dir("vae"));
    GAPS_RETURN_IF_ERROR(in_component("vae", vae.status()));
    p->vae_ = *std::move(vae);
  }
  GAPS_RETURN_IF_ERROR(in_component("controlnet", p->load_controlnet(folder)));
  GAPS_RETURN_IF_ERROR(p->load_ip_adapter(model_options));
  return p;
}

at::TensorOptions SdxlPipeline::convolution_options() const {
  const at::TensorOptions o = at::TensorOptions().dtype(options_.dtype).device(options_.device);
  return options_.channels_last ? o.memory_format(at::MemoryFormat::ChannelsLast) : o;
}

absl::Status SdxlPipeline::load_controlnet(const ModelFolder& folder) {
  std::string dir = options_.controlnet;
  if (dir.empty() && folder.index().contains("controlnet")) {
    GAPS_RETURN_IF_ERROR(expect_class(folder, "controlnet", "ControlNetModel"));
    dir = folder.component_dir("controlnet");
  }
  if (dir.empty()) return absl::OkStatus();
  GAPS_ASSIGN_OR_RETURN(ControlNet net, ControlNet::load_folder(dir, convolution_options(), options_.variant));
  if (absl::Status fits = net.check_compatible(unet_->config()); !fits.ok()) {
    return absl::Status(fits.code(), absl::StrCat(dir, ": ", fits.message()));
  }
  if (net.config().downscale() != latent_factor()) {
    return absl::InvalidArgumentError(absl::StrCat(dir, ": the ControlNet's conditioning embedding downscales by ",
                                                   net.config().downscale(), ", the VAE by ", latent_factor()));
  }
  controlnet_ = std::move(net);
  return absl::OkStatus();
}

absl::Status SdxlPipeline::check_control(const ControlInput& control, const at::Tensor& images) const {
  if (!controlnet_)
    return absl::FailedPreconditionError("img2img: a control image was given but no ControlNet is loaded");
  const int64_t channels = controlnet_->config().conditioning_channels;
  const at::Tensor& c = control.image;
  if (!c.defined() || c.dim() != 4 || c.size(0) != images.size(0) || c.size(1) != channels ||
      c.size(2) != images.size(2) || c.size(3) != images.size(3)) {
    return absl::InvalidArgumentError(absl::StrCat("img2img: the control image must be B x ", channels,
                                                   " x H x W like the images (", images.size(0), " x 3 x ",
                                                   images.size(2), " x ", images.size(3), ")"));
  }
  if (control.scales.size() != 1 && static_cast<int64_t>(control.scales.size()) != images.size(0)) {
    return absl::InvalidArgumentError("img2img: give one conditioning scale, or one per image");
  }
  for (double s : control.scales) {
    if (!std::isfinite(s)) return absl::InvalidArgumentError("img2img: conditioning scales must be finite");
  }
  return absl::OkStatus();
}

absl::Status SdxlPipeline::load_ip_adapter(at::TensorOptions model_options) {
  if (options_.ip_adapter.empty() != options_.image_encoder.empty()) {
    return absl::InvalidArgumentError("SDXL pipeline: an IP-Adapter needs both its weight file and its image encoder");
  }
  if (options_.ip_adapter.empty()) return absl::OkStatus();
  auto encoder = ClipVisionEncoder::load_folder(options_.image_encoder, model_options);
  GAPS_RETURN_IF_ERROR(in_component("image_encoder", encoder.status()));
  auto adapter = IpAdapter::load(options_.ip_adapter, *unet_, model_options);
  GAPS_RETURN_IF_ERROR(in_component("ip_adapter", adapter.status()));
  if ((*adapter)->image_embed_dim() != encoder->config().projection_dim) {
    return absl::InvalidArgumentError(
        absl::StrCat(options_.ip_adapter, " projects image embeddings of size ", (*adapter)->image_embed_dim(),
                     ", the image encoder ", options_.image_encoder, " makes ", encoder->config().projection_dim));
  }
  image_encoder_ = *std::move(encoder);
  ip_adapter_ = *std::move(adapter);
  return absl::OkStatus();
}

absl::Status SdxlPipeline::set_image_prompts(const Img2ImgParams& params, int64_t batch) {
  const auto& refs = params.reference_images;
  const bool any = std::any_of(refs.begin(), refs.end(), [](const at::Tensor& r) { return r.defined(); });
  if (!ip_adapter_) {
    if (any)
      return absl::FailedPreconditionError("img2img: reference images need a pipeline loaded with an IP-Adapter");
    return absl::OkStatus();
  }
  const auto& scales = params.ip_adapter_scales;
  if (!refs.empty() && static_cast<int64_t>(refs.size()) != batch) {
    return absl::InvalidArgumentError("img2img: give one reference image per image (undefined for none), or none");
  }
  if (scales.size() != 1 && static_cast<int64_t>(scales.size()) != batch) {
    return absl::InvalidArgumentError("img2img: give one IP-Adapter scale, or one per image");
  }
  c10::InferenceMode inference;
  const at::TensorOptions model_options = at::TensorOptions().dtype(options_.dtype).device(options_.device);
  at::Tensor embeds = at::zeros({batch, ip_adapter_->image_embed_dim()}, model_options);
  std::vector<float> image_scales(batch, 0.0f);
  std::vector<at::Tensor> images;
  std::vector<int64_t> with_reference;
  for (int64_t i = 0; i < static_cast<int64_t>(refs.size()); ++i) {
    if (!refs[i].defined()) continue;
    images.push_back(refs[i]);
    with_reference.push_back(i);
    image_scales[i] = static_cast<float>(scales.size() == 1 ? scales[0] : scales[i]);
  }
  if (!images.empty()) {
    auto encoded = image_encoder_->embed(images);
    if (!encoded.ok())
      return absl::InvalidArgumentError(absl::StrCat("img2img reference image: ", encoded.status().message()));
    embeds.index_copy_(0, at::tensor(with_reference, at::kLong).to(options_.device), encoded->to(model_options));
  }
  at::Tensor tokens = ip_adapter_->project(embeds);
  at::Tensor scale = at::tensor(image_scales).to(model_options);
  if (params.guidance_scale > 1.0) {  // the batch of denoise(): negatives first
    tokens = at::cat({ip_adapter_->project(at::zeros_like(embeds)), tokens});
    scale = at::cat({scale, scale});
  }
  ip_adapter_->set_image_prompt(tokens, scale);
  return absl::OkStatus();
}

absl::Status SdxlPipeline::set_cuda_graphs(bool on) {
  if (!on) {
    graphs_.reset();
    return absl::OkStatus();
  }
#if defined(GAPS_CUDA_KERNELS)
  if (!options_.device.is_cuda()) return absl::InvalidArgumentError("SDXL pipeline: CUDA graphs need a CUDA device");
  if (!graphs_) graphs_ = std::make_shared<UNetGraphs>();
  return absl::OkStatus();
#else
  return absl::UnimplementedError("SDXL pipeline: CUDA graphs need a CUDA build of gaps");
#endif
}

at::Tensor SdxlPipeline::run_unet(const UNetInputs& in) {
#if defined(GAPS_CUDA_KERNELS)
  if (graphs_) return graphs_->run(*unet_, in);
#endif
  return unet_->forward(in);
}

PromptEmbeddings SdxlPipeline::encode_prompts(const std::vector<std::string>& prompts) const {
  const ClipTextOutput one = text_encoder_->forward(token_tensor(*tokenizer_, prompts));
  const ClipTextOutput two = text_encoder_2_->forward(token_tensor(*tokenizer_2_, prompts));
  return {at::cat({one.penultimate, two.penultimate}, -1), two.text_embeds};
}

namespace {

// diffusers' randn_tensor with CPU generators, in float32: per generator, first the latent-distribution
// sample, then the noise. One generator draws each for the whole batch; a list draws image by image.
std::pair<at::Tensor, at::Tensor> draw_latent_and_noise(at::IntArrayRef shape, const std::vector<uint64_t>& seeds) {
  if (seeds.size() == 1) {
    at::Generator g = at::make_generator<at::CPUGeneratorImpl>(seeds[0]);
    at::Tensor latent = at::randn(shape, g, at::kFloat);
    return {latent, at::randn(shape, g, at::kFloat)};
  }
  std::vector<int64_t> one = shape.vec();
  one[0] = 1;
  std::vector<at::Tensor> latent, noise;
  for (uint64_t seed : seeds) {
    at::Generator g = at::make_generator<at::CPUGeneratorImpl>(seed);
    latent.push_back(at::randn(one, g, at::kFloat));
    noise.push_back(at::randn(one, g, at::kFloat));
  }
  return {at::cat(latent), at::cat(noise)};
}

}  // namespace

absl::StatusOr<at::Tensor> SdxlPipeline::img2img(const at::Tensor& images, const std::vector<std::string>& prompts,
                                                 const Img2ImgParams& params, const std::vector<uint64_t>& seeds,
                                                 const std::optional<ControlInput>& control) {
  if (images.dim() != 4 || images.size(1) != 3)
    return absl::InvalidArgumentError("img2img: images must be B x 3 x H x W");
  const int64_t batch = images.size(0), height = images.size(2), width = images.size(3), f = latent_factor();
  if (height % f != 0 || width % f != 0) {
    return absl::InvalidArgumentError(
        absl::StrCat("img2img: image size ", height, "x", width, " is not a multiple of ", f));
  }
  if (prompts.size() != 1 && static_cast<int64_t>(prompts.size()) != batch) {
    return absl::InvalidArgumentError("img2img: give one prompt, or one per image");
  }
  if (seeds.size() != 1 && static_cast<int64_t>(seeds.size()) != batch) {
    return absl::InvalidArgumentError("img2img: give one seed, or one per image");
  }
  if (control) GAPS_RETURN_IF_ERROR(check_control(*control, images));
  if (params.steps < 1) return absl::InvalidArgumentError("img2img: steps must be >= 1");
  GAPS_ASSIGN_OR_RETURN(std::vector<Cohort> cohorts, make_cohorts(params, batch));
  GAPS_RETURN_IF_ERROR(set_image_prompts(params, batch));
  at::Tensor result;
  {
    // No autograd bookkeeping; the result is cloned outside, so callers get an ordinary tensor.
    c10::InferenceMode inference;
    const std::vector<std::string> all_prompts =
        prompts.size() == 1 ? std::vector<std::string>(batch, prompts[0]) : prompts;
    const at::Tensor moments = vae_->encode_moments((images.to(options_.device, at::kFloat) * 2 - 1).to(vae_->dtype()));
    const auto parts = moments.chunk(2, 1);
    const at::Tensor mean = parts[0].to(at::kCPU, at::kFloat);
    const at::Tensor std = at::exp(0.5 * at::clamp(parts[1].to(at::kCPU, at::kFloat), -30.0, 20.0));
    const auto [latent_draw, noise] = draw_latent_and_noise(mean.sizes(), seeds);
    const double scaling = vae_->config().scaling_factor;
    const at::Tensor clean = (mean + std * latent_draw) * scaling;
    at::Tensor latents = at::empty_like(clean);
    for (const Cohort& c : cohorts) {
      const at::Tensor rows = at::tensor(c.rows, at::kLong);
      latents.index_copy_(0, rows,
                          c.scheduler->add_noise(clean.index_select(0, rows), noise.index_select(0, rows), c.start));
    }
    latents = denoise(cohorts, latents.to(options_.device, options_.dtype), all_prompts, height, width,
                      params.guidance_scale, control);
    const at::Tensor decoded = vae_->decode((latents / scaling).to(vae_->dtype()));
    result = (decoded.to(at::kCPU, at::kFloat) / 2 + 0.5).clamp(0, 1);
  }
  return result.clone();
}

absl::StatusOr<std::vector<SdxlPipeline::Cohort>> SdxlPipeline::make_cohorts(const Img2ImgParams& params,
                                                                             int64_t batch) const {
  if (!params.strengths.empty() && static_cast<int64_t>(params.strengths.size()) != batch)
    return absl::InvalidArgumentError("img2img: give one strength per image, or none");
  std::map<int64_t, std::vector<int64_t>> rows_by_start;
  for (int64_t b = 0; b < batch; ++b) {
    const double strength = params.strengths.empty() ? params.strength : params.strengths[b];
    if (!(strength > 0 && strength <= 1)) {
      return absl::InvalidArgumentError(absl::StrCat("img2img: strength ", strength, " is not in (0, 1]"));
    }
    // diffusers' get_timesteps: the last int(steps * strength) steps of the schedule.
    const int64_t run_steps = std::min<int64_t>(static_cast<int64_t>(params.steps * strength), params.steps);
    if (run_steps < 1) {
      return absl::InvalidArgumentError(
          absl::StrCat("img2img: strength ", strength, " with ", params.steps, " steps leaves no step to run"));
    }
    rows_by_start[params.steps - run_steps].push_back(b);
  }
  std::vector<Cohort> cohorts;
  for (auto& [start, rows] : rows_by_start) {
    GAPS_ASSIGN_OR_RETURN(std::unique_ptr<Scheduler> scheduler, make_scheduler(scheduler_config_));
    scheduler->set_timesteps(params.steps);
    cohorts.push_back(Cohort{start, std::move(scheduler), std::move(rows)});
  }
  return cohorts;
}

at::Tensor SdxlPipeline::denoise(std::vector<Cohort>& cohorts, at::Tensor latents,
                                 const std::vector<std::string>& prompts, int64_t height, int64_t width,
                                 double guidance_scale, const std::optional<ControlInput>& control) {
  const bool cfg = guidance_scale > 1.0;
  const PromptEmbeddings cond = encode_prompts(prompts);
  UNetInputs in;
  in.encoder_hidden_states = cond.context;
  in.text_embeds = cond.pooled;
  if (cfg) {
    const PromptEmbeddings uncond = force_zeros_for_empty_prompt_
                                        ? PromptEmbeddings{at::zeros_like(cond.context), at::zeros_like(cond.pooled)}
                                        : encode_prompts(std::vector<std::string>(prompts.size(), ""));
    in.encoder_hidden_states = at::cat({uncond.context, cond.context});
    in.text_embeds = at::cat({uncond.pooled, cond.pooled});
  }
  // Micro-conditioning: original size = target size = the image's, crop (0, 0).
  const auto h = static_cast<float>(height), w = static_cast<float>(width);
  in.time_ids = at::tensor(std::vector<float>{h, w, 0.0f, 0.0f, h, w})
                    .view({1, 6})
                    .expand({in.encoder_hidden_states.size(0), 6})
                    .contiguous()
                    .to(options_.device);
  // The ControlNet runs on the UNet's batch (both guidance halves); all-zero scales add nothing, so skip it.
  at::Tensor control_image, control_scale;
  if (control && std::any_of(control->scales.begin(), control->scales.end(), [](double s) { return s != 0.0; })) {
    const int64_t batch = latents.size(0);
    control_image = control->image.to(options_.device, options_.dtype);
    control_scale = at::tensor(control->scales, at::kDouble).expand({batch}).contiguous();
    if (cfg) {
      control_image = at::cat({control_image, control_image});
      control_scale = at::cat({control_scale, control_scale});
    }
  }
  // Cohorts are ordered by start; the first one's scheduler gives every step's timestep and input scale (all
  // share the schedule), which a cohort that has not started yet gets too, its output discarded.
  const Scheduler& schedule = *cohorts.front().scheduler;
  const auto steps = static_cast<int64_t>(schedule.timesteps().size());
  std::vector<at::Tensor> rows;
  for (const Cohort& c : cohorts) rows.push_back(at::tensor(c.rows, at::kLong).to(options_.device));
  for (int64_t i = cohorts.front().start; i < steps; ++i) {
    in.sample = schedule.scale_model_input(cfg ? at::cat({latents, latents}) : latents, i);
    in.timestep = at::scalar_tensor(schedule.timesteps()[i], at::TensorOptions().device(options_.device));
    if (control_image.defined()) {
      ControlNetResiduals residuals = controlnet_->forward(in, control_image, control_scale);
      in.down_block_residuals = std::move(residuals.down);
      in.mid_block_residual = residuals.mid;
    }
    at::Tensor prediction = run_unet(in);
    if (cfg) prediction = classifier_free_guidance(prediction, guidance_scale);
    if (cohorts.size() == 1) {
      latents = cohorts.front().scheduler->step(prediction, i, latents);
      continue;
    }
    at::Tensor next = latents.clone();
    for (size_t c = 0; c < cohorts.size() && cohorts[c].start <= i; ++c) {
      next.index_copy_(
          0, rows[c],
          cohorts[c].scheduler->step(prediction.index_select(0, rows[c]), i, latents.index_select(0, rows[c])));
    }
    latents = next;
  }
  return latents;
}

absl::Status SdxlPipeline::reset_lora() {
  if (lora_) {
    lora_->unmerge_from(*unet_);
    lora_->detach_from(*unet_);
  }
  lora_.reset();
  if (graphs_) {
    graphs_.reset();
    GAPS_RETURN_IF_ERROR(set_cuda_graphs(true));
  }
  return absl::OkStatus();
}

absl::Status SdxlPipeline::load_lora(const std::string& path) {
  GAPS_RETURN_IF_ERROR(reset_lora());
  GAPS_ASSIGN_OR_RETURN(UNetLora lora, UNetLora::load(path, *unet_));
  return apply_lora(std::move(lora));
}

absl::Status SdxlPipeline::load_lora_bytes(std::string bytes, const std::string& source) {
  GAPS_RETURN_IF_ERROR(reset_lora());
  GAPS_ASSIGN_OR_RETURN(UNetLora lora, UNetLora::from_bytes(std::move(bytes), *unet_, source));
  return apply_lora(std::move(lora));
}

absl::Status SdxlPipeline::apply_lora(UNetLora lora) {
  lora_ = std::move(lora);
  lora_->merge_into(*unet_, &lora_base_copies_);
  return absl::OkStatus();
}

absl::StatusOr<std::vector<double>> SdxlPipeline::train_lora(const at::Tensor& images,
                                                             const std::vector<std::string>& prompts,
                                                             const std::optional<ControlInput>& control,
                                                             const LoraConfig& config,
                                                             const LoraTrainingOptions& options) {
  if (images.dim() != 4 || images.size(1) != 3)
    return absl::InvalidArgumentError("LoRA training: images must be B x 3 x H x W");
  const int64_t batch = images.size(0), height = images.size(2), width = images.size(3), f = latent_factor();
  if (height % f != 0 || width % f != 0) {
    return absl::InvalidArgumentError(
        absl::StrCat("LoRA training: image size ", height, "x", width, " is not a multiple of ", f));
  }
  if (prompts.size() != 1 && static_cast<int64_t>(prompts.size()) != batch) {
    return absl::InvalidArgumentError("LoRA training: give one prompt, or one per image");
  }
  if (control) {
    GAPS_RETURN_IF_ERROR(check_control(*control, images));
    if (control->scales.size() != 1) return absl::InvalidArgumentError("LoRA training: give one conditioning scale");
  }
  GAPS_ASSIGN_OR_RETURN(std::unique_ptr<Scheduler> scheduler, make_scheduler(scheduler_config_));
  const at::TensorOptions model_options = at::TensorOptions().dtype(options_.dtype).device(options_.device);
  LoraTrainingData data;
  {
    at::NoGradGuard frozen;
    const at::Tensor moments = vae_->encode_moments((images.to(options_.device, at::kFloat) * 2 - 1).to(vae_->dtype()));
    at::Generator generator = at::make_generator<at::CPUGeneratorImpl>(options.seed);
    const at::Tensor latents = vae_->sample_latents(moments.to(at::kCPU, at::kFloat), generator);
    data.latents = (latents * vae_->config().scaling_factor).to(model_options);
    const PromptEmbeddings cond =
        encode_prompts(prompts.size() == 1 ? std::vector<std::string>(batch, prompts[0]) : prompts);
    data.encoder_hidden_states = cond.context;
    data.text_embeds = cond.pooled;
    const auto h = static_cast<float>(height), w = static_cast<float>(width);
    data.time_ids =
        at::tensor(std::vector<float>{h, w, 0.0f, 0.0f, h, w}).view({1, 6}).expand({batch, 6}).to(model_options);
    if (control) {
      data.control_images = control->image.to(model_options);
      data.conditioning_scale = control->scales[0];
    }
  }
  GAPS_RETURN_IF_ERROR(reset_lora());
  // The adapters learn the scene under the text (and depth) conditioning the paper trains with; the image
  // prompt joins at generation (img2img sets it anew). Its buffers are inference tensors, which autograd
  // could not save for backward anyway.
  if (ip_adapter_) ip_adapter_->set_text_only();
  GAPS_ASSIGN_OR_RETURN(UNetLora lora, UNetLora::create(*unet_, config, options.seed));
  std::vector<double> losses;
  {
    LoraTrainer trainer(*unet_, lora, scheduler->alphas_cumprod().to(options_.device),
                        control ? &*controlnet_ : nullptr, options);
    auto trained = trainer.train(data);
    if (!trained.ok()) {
      lora.detach_from(*unet_);
      return trained.status();
    }
    losses = *std::move(trained);
  }
  lora_ = std::move(lora);
  lora_->merge_into(*unet_, &lora_base_copies_);
  return losses;
}

}  // namespace gaps::sdxl

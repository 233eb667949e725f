#include "diffusion_worker/sdxl_generator.h"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <limits>
#include <map>
#include <optional>
#include <utility>

#include <ATen/ATen.h>
#include <nlohmann/json.hpp>
#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "absl/strings/str_join.h"
#include "common/io_util.h"
#include "common/status_macros.h"
#include "diffusion_worker/sdxl/two_stage.h"

namespace gaps {
namespace {

absl::Status option_error(const std::string& key, const std::string& what) {
  return absl::InvalidArgumentError(absl::StrCat("sdxl option '", key, "': ", what));
}

const std::pair<const char*, at::ScalarType> kDtypes[] = {
    {"float32", at::kFloat}, {"float16", at::kHalf}, {"bfloat16", at::kBFloat16}};

std::vector<std::string> dtype_names() {
  std::vector<std::string> names;
  for (const auto& [name, type] : kDtypes) names.push_back(name);
  return names;
}

// Parsed options hold one of kDtypes' names already (the table's choices); options built in code may not.
absl::StatusOr<at::ScalarType> parse_dtype(const std::string& name, const std::string& key = "dtype") {
  for (const auto& [dtype_name, type] : kDtypes)
    if (name == dtype_name) return type;
  return option_error(key, absl::StrCat("'", name, "' is not one of ", absl::StrJoin(dtype_names(), ", ")));
}

std::vector<std::string> vae_dtype_names() {
  std::vector<std::string> names = {""};
  for (const std::string& name : dtype_names()) names.push_back(name);
  return names;
}

// "" = the pipeline's choice (unset).
absl::StatusOr<std::optional<at::ScalarType>> parse_vae_dtype(const std::string& name) {
  if (name.empty()) return std::nullopt;
  return parse_dtype(name, "vae_dtype");
}

}  // namespace

const OptionTable<SdxlOptions>& sdxl_option_table() {
  using O = SdxlOptions;
  static const OptionTable<O> table(
      "sdxl",
      {
          string_option<O>("weights", &O::weights, "diffusers SDXL folder (required)"),
          integer_option<O>("steps", &O::steps, at_least(1),
                            "steps of the full schedule; a request runs steps x strength"),
          number_option<O>("guidance", &O::guidance, at_least(0), "classifier-free guidance scale"),
          string_option<O>("dtype", &O::dtype, "weights' and activations' type (half types on CUDA only)",
                           dtype_names()),
          string_option<O>("vae_dtype", &O::vae_dtype,
                           "the VAE's type; \"\" = float32 when its config asks for force_upcast (SDXL's does), "
                           "else dtype (half types on CUDA only)",
                           vae_dtype_names()),
          string_option<O>("device", &O::device, "cpu, cuda or cuda:N"),
          string_option<O>("prompt", &O::prompt, "prompt of requests without one"),
          string_option<O>("variant", &O::variant, "fp16 = the *.fp16.safetensors weight copies"),
          string_option<O>("scheduler", &O::scheduler, "euler, ddim, dpmpp2m or pndm; \"\" = the folder's"),
          integer_option<O>("batch_size", &O::batch_size, at_least(1), "requests denoised together"),
          number_option<O>("batch_step_overhead", &O::batch_step_overhead, at_least(0),
                           "a denoising step's fixed cost in batch members, above which requests of unequal "
                           "strengths share a batch; unset = 1 on CUDA, 0 on the CPU"),
          bool_option<O>("cuda_graphs", &O::cuda_graphs, "replay the UNet from CUDA graphs (CUDA only)"),
          bool_option<O>("channels_last", &O::channels_last,
                         "the UNet's, ControlNet's and VAE's convolutions and activations in channels-last order"),
          string_option<O>("controlnet", &O::controlnet, "depth ControlNet folder; \"\" = the SDXL folder's, if any"),
          number_option<O>(
              "control_min_alpha", [](auto& o) -> auto& { return o.depth_control.min_alpha; }, above(0),
              "tau_alpha: less rendered alpha = 0 in the depth image"),
          integer_option<O>(
              "control_variance_window", [](auto& o) -> auto& { return o.depth_control.variance_window; },
              odd_at_least(1), "side of the window of the local depth variance"),
          number_option<O>(
              "control_max_relative_variance", [](auto& o) -> auto& { return o.depth_control.max_relative_variance; },
              at_least(0), "larger Var(d) / mean(d)^2 over the window = 0 in the depth image"),
          string_option<O>("ip_adapter", &O::ip_adapter, "IP-Adapter weight file; needs image_encoder"),
          string_option<O>("image_encoder", &O::image_encoder, "the IP-Adapter's CLIP image encoder folder"),
          number_option<O>("ip_adapter_scale", &O::ip_adapter_scale, at_least(0),
                           "lambda_ip, the image prompt's scale, for requests without one"),
          string_option<O>("inpaint", &O::inpaint, "SD2 inpainting folder for two-stage generation; \"\" = off"),
          number_option<O>("inpaint_depth_threshold", &O::inpaint_depth_threshold, at_least(0),
                           "tau_d for requests without inpaint settings"),
          string_option<O>("inpaint_scheduler", &O::inpaint_scheduler, "the inpainting scheduler; \"\" = the folder's"),
          integer_option<O>("inpaint_steps", &O::inpaint_steps, at_least(1), "steps of the inpainting schedule"),
          number_option<O>("inpaint_guidance", &O::inpaint_guidance, at_least(0), "guidance of the inpainting"),
          number_option<O>("inpaint_uncovered_fraction", &O::inpaint_uncovered_fraction, between(0, 1, "[)"),
                           "inpaint views more uncovered than this (requests without inpaint settings)"),
          integer_option<O>("inpaint_dilation", &O::inpaint_dilation, odd_at_least(1),
                            "side of the uncovered mask's dilation (requests without inpaint settings)"),
          integer_option<O>("lora_steps", &O::lora_steps, at_least(0),
                            "LoRA scene adaptation steps of adapt() calls without the job's; 0 = none"),
          integer_option<O>(
              "lora_rank", &O::lora_rank, at_least(1),
              "rank of the LoRA adapters (cross-attention to_q/to_k/to_v/to_out) of adapt() calls without the job's"),
          number_option<O>("lora_lr", &O::lora_lr, above(0), "Adam learning rate of the adapters"),
          bool_option<O>("lora_cuda_graph", &O::lora_cuda_graph,
                         "on a CUDA device, replay LoRA training's steps from one CUDA graph"),
          string_option<O>("lora_save", &O::lora_save, "file the trained adapters are saved to; not with lora"),
          string_option<O>("lora", &O::lora, "LoRA file attached at start-up (all its adapters); not with lora_steps"),
          string_option<O>("depth_anything", &O::depth_anything,
                           "Depth-Anything folder: LoRA training's control images from its depth"),
          string_option<O>("depth_cache", &O::depth_cache, "folder of Depth-Anything's maps; needs depth_anything"),
      });
  return table;
}

absl::StatusOr<SdxlOptions> parse_sdxl_options(const std::string& json) {
  const nlohmann::json j = nlohmann::json::parse(json, nullptr, /*allow_exceptions=*/false);
  if (j.is_discarded() || !j.is_object()) {
    return absl::InvalidArgumentError(
        absl::StrCat("sdxl options must be a JSON object with at least \"weights\", got: ", json));
  }
  SdxlOptions o;
  GAPS_RETURN_IF_ERROR(sdxl_option_table().apply(j, o));
  if (o.weights.empty()) return option_error("weights", "the SDXL model folder is required");
  if (o.ip_adapter.empty() != o.image_encoder.empty()) {
    return option_error(o.ip_adapter.empty() ? "image_encoder" : "ip_adapter",
                        "an IP-Adapter needs both ip_adapter (weights) and image_encoder (CLIP image encoder folder)");
  }
  if (o.lora_steps > 0 && !o.lora.empty()) {
    return option_error("lora", "give either a LoRA file to load or lora_steps to train one, not both");
  }
  // With a LoRA file attached nothing is trained, whatever a job asks.
  if (!o.lora_save.empty() && !o.lora.empty())
    return option_error("lora_save", "nothing is trained with a LoRA file attached (option lora)");
  if (!o.depth_anything.empty() && (o.controlnet.empty() || !o.lora.empty())) {
    return option_error("depth_anything",
                        "conditions LoRA training: it needs a controlnet, and no LoRA file attached (option lora)");
  }
  if (!o.depth_cache.empty() && o.depth_anything.empty()) return option_error("depth_cache", "needs depth_anything");
  return o;
}

SdxlGenerator::SdxlGenerator(SdxlOptions options, std::unique_ptr<sdxl::SdxlPipeline> pipeline)
    : options_(std::move(options)), pipeline_(std::move(pipeline)), depth_cache_(options_.depth_cache) {}

absl::StatusOr<std::unique_ptr<SdxlGenerator>> SdxlGenerator::create(const SdxlOptions& options) {
  GAPS_ASSIGN_OR_RETURN(const at::ScalarType dtype, parse_dtype(options.dtype));
  at::Device device(at::kCPU);
  try {
    device = at::Device(options.device);
  } catch (const std::exception&) {
    return option_error("device", absl::StrCat("'", options.device, "' is not a device (cpu, cuda, cuda:N)"));
  }
  if (device.is_cuda() && !at::hasCUDA())
    return option_error("device", "CUDA requested but no CUDA device is available");
  if (!device.is_cuda() && !device.is_cpu()) return option_error("device", "only cpu and cuda are supported");
  if (device.is_cpu() && dtype != at::kFloat) return option_error("dtype", "the CPU path runs in float32 only");
  GAPS_ASSIGN_OR_RETURN(const std::optional<at::ScalarType> vae_dtype, parse_vae_dtype(options.vae_dtype));
  if (device.is_cpu() && vae_dtype && *vae_dtype != at::kFloat)
    return option_error("vae_dtype", "the CPU path runs in float32 only");
  auto pipeline = sdxl::SdxlPipeline::load(
      options.weights,
      sdxl::PipelineOptions{dtype, device, options.scheduler, options.cuda_graphs, options.variant, options.controlnet,
                            options.ip_adapter, options.image_encoder, vae_dtype, options.channels_last});
  if (!pipeline.ok()) {
    return absl::Status(
        pipeline.status().code(),
        absl::StrCat("sdxl backend: ", options.weights, " is not a usable SDXL model: ", pipeline.status().message()));
  }
  if (!options.lora.empty()) {
    if (absl::Status s = (*pipeline)->load_lora(options.lora); !s.ok()) {
      return absl::Status(s.code(), absl::StrCat("sdxl option 'lora': ", s.message()));
    }
  }
  std::unique_ptr<SdxlGenerator> generator(new SdxlGenerator(options, *std::move(pipeline)));
  if (!options.depth_anything.empty()) {
    auto model = depth::DepthAnything::load(options.depth_anything);
    if (!model.ok()) {
      return absl::Status(model.status().code(),
                          absl::StrCat("sdxl option 'depth_anything': ", model.status().message()));
    }
    generator->depth_model_ = *std::move(model);
  }
  return generator;
}

std::string SdxlGenerator::name() const {
  std::string name = pipeline_->controlnet() ? "sdxl 1 controlnet" : "sdxl 1";
  if (options_.lora.empty() && pipeline_->controlnet())
    absl::StrAppend(&name, depth_model_ ? " lora-depth:depth-anything" : " lora-depth:rendered");
  return name;
}

std::string SdxlGenerator::weights_identity() const {
  std::string out = absl::StrCat("sdxl=", options_.weights);
  const std::pair<const char*, const std::string*> parts[] = {{"controlnet", &options_.controlnet},
                                                              {"ip_adapter", &options_.ip_adapter},
                                                              {"image_encoder", &options_.image_encoder},
                                                              {"lora", &options_.lora},
                                                              {"depth_anything", &options_.depth_anything}};
  for (const auto& [component, path] : parts)
    if (!path->empty()) absl::StrAppend(&out, "\n", component, "=", *path);
  if (!options_.inpaint.empty())
    absl::StrAppend(&out, "\ninpaint=", options_.inpaint, inpaint_ ? " (loaded)" : " (on first need)");
  return out;
}

absl::Status SdxlGenerator::adapt(const std::vector<ReferenceView>& views,
                                  const std::optional<SceneAdaptation>& adaptation) {
  notes_.clear();
  if (views.empty()) return absl::InvalidArgumentError("sdxl adapt: no ground-truth views");
  for (size_t i = 0; i < views.size(); ++i) {
    const at::Tensor& image = views[i].image;
    if (!image.defined() || image.dim() != 3 || image.size(2) != 3) {
      return absl::InvalidArgumentError(absl::StrCat("sdxl adapt: view ", i, " image is not H x W x 3"));
    }
  }
  const SceneAdaptation lora =
      adaptation.value_or(SceneAdaptation{static_cast<int>(options_.lora_rank), static_cast<int>(options_.lora_steps)});
  if (absl::Status range = check_scene_adaptation(lora); !range.ok())
    return absl::InvalidArgumentError(absl::StrCat("sdxl adapt: ", range.message()));
  if (!options_.lora.empty()) {
    if (lora.lora_steps > 0) {
      notes_.push_back(absl::StrCat("sdxl keeps the LoRA file attached at start-up (option lora: ", options_.lora,
                                    "): the ", lora.lora_steps, " LoRA steps asked for were not trained"));
    }
    return absl::OkStatus();
  }
  // Without training, a previous scene's adapters must not shape this scene's images.
  if (lora.lora_steps == 0) return pipeline_->reset_lora();
  return train_lora(views, lora);
}

absl::StatusOr<std::string> SdxlGenerator::export_adaptation() const {
  if (!options_.lora.empty() || pipeline_->lora() == nullptr) return std::string();
  return pipeline_->lora()->to_bytes();
}

absl::Status SdxlGenerator::install_adaptation(const std::vector<ReferenceView>& views,
                                               const std::optional<SceneAdaptation>& adaptation, std::string exported) {
  if (!options_.lora.empty() || exported.empty()) return adapt(views, adaptation);
  notes_.clear();
  GAPS_RETURN_IF_ERROR(pipeline_->load_lora_bytes(std::move(exported), "the adapters another worker trained"));
  if (options_.lora_save.empty()) return absl::OkStatus();
  return pipeline_->lora()->save(options_.lora_save);
}

absl::StatusOr<at::Tensor> SdxlGenerator::view_disparity(const at::Tensor& image, size_t index) {
  const at::Tensor pixels = image.to(at::kCPU, at::kFloat).clamp(0, 1).contiguous();
  // Keyed by the depth model and the pixels: the same view misses nothing, a changed one shares nothing.
  const std::string model_key = absl::StrFormat("model-%016x", fnv1a(options_.depth_anything));
  const std::string view_key =
      absl::StrFormat("%dx%d-%016x", pixels.size(0), pixels.size(1), fnv1a(pixels.const_data_ptr(), pixels.nbytes()));
  auto disparity = depth_cache_.get_or_compute(model_key, view_key, pixels.size(0), pixels.size(1),
                                               [&] { return depth_model_->estimate_depth(pixels); });
  if (!disparity.ok()) {
    return absl::Status(disparity.status().code(),
                        absl::StrCat("sdxl adapt: Depth-Anything on view ", index, ": ", disparity.status().message()));
  }
  return *disparity;
}

absl::StatusOr<at::Tensor> SdxlGenerator::training_control_image(const ReferenceView& v, size_t index) {
  if (depth_model_) {
    GAPS_ASSIGN_OR_RETURN(const at::Tensor disparity, view_disparity(v.image, index));
    GAPS_ASSIGN_OR_RETURN(DepthControl control, disparity_control_image(disparity));
    return control.image;
  }
  const auto hw = v.image.sizes().slice(0, 2);
  if (!v.render_depth.defined() || !v.render_alpha.defined() || v.render_depth.sizes() != hw ||
      v.render_alpha.sizes() != hw) {
    return absl::InvalidArgumentError(absl::StrCat(
        "sdxl adapt: view ", index, " needs render_depth and render_alpha of its image's size (ControlNet)"));
  }
  GAPS_ASSIGN_OR_RETURN(DepthControl control,
                        depth_control_image(v.render_depth, v.render_alpha, options_.depth_control));
  return control.image;
}

absl::Status SdxlGenerator::train_lora(const std::vector<ReferenceView>& views, const SceneAdaptation& adaptation) {
  const int64_t height = views[0].image.size(0), width = views[0].image.size(1), f = pipeline_->latent_factor();
  const std::vector<int64_t> pad{0, (width + f - 1) / f * f - width, 0, (height + f - 1) / f * f - height};
  std::vector<at::Tensor> images, controls;
  for (size_t i = 0; i < views.size(); ++i) {
    const ReferenceView& v = views[i];
    if (v.image.size(0) != height || v.image.size(1) != width) {
      return absl::InvalidArgumentError(absl::StrCat("sdxl adapt: LoRA training needs views of one size; view ", i,
                                                     " is ", v.image.size(0), "x", v.image.size(1), ", view 0 ", height,
                                                     "x", width));
    }
    images.push_back(at::replication_pad2d(v.image.to(at::kFloat).clamp(0, 1).permute({2, 0, 1}).unsqueeze(0), pad));
    if (pipeline_->controlnet()) {
      GAPS_ASSIGN_OR_RETURN(const at::Tensor control, training_control_image(v, i));
      controls.push_back(at::replication_pad2d(control.unsqueeze(0), pad));
    }
  }
  std::optional<sdxl::ControlInput> control;
  if (pipeline_->controlnet()) control = sdxl::ControlInput{at::cat(controls), {1.0}};
  sdxl::LoraConfig config;
  config.rank = adaptation.lora_rank;
  config.alpha = static_cast<double>(adaptation.lora_rank);
  sdxl::LoraTrainingOptions training;
  training.steps = adaptation.lora_steps;
  training.learning_rate = options_.lora_lr;
  training.cuda_graph = options_.lora_cuda_graph && pipeline_->device().is_cuda();
  GAPS_ASSIGN_OR_RETURN(const std::vector<double> losses,
                        pipeline_->train_lora(at::cat(images), {options_.prompt}, control, config, training));
  if (options_.lora_save.empty()) return absl::OkStatus();
  return pipeline_->lora()->save(options_.lora_save);
}

namespace {

double seconds_since(std::chrono::steady_clock::time_point start) {
  return std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
}

}  // namespace

std::vector<size_t> img2img_batch_ends(const std::vector<int64_t>& steps, size_t batch_size, double step_overhead) {
  const size_t n = steps.size();
  std::vector<double> best(n + 1, 0.0);
  std::vector<size_t> begin_of(n + 1, 0);
  for (size_t j = 1; j <= n; ++j) {
    best[j] = std::numeric_limits<double>::infinity();
    // Ties go to the earliest begin: fewer, larger batches for the same cost.
    for (size_t i = j > batch_size ? j - batch_size : 0; i < j; ++i) {
      const double cost = best[i] + static_cast<double>(steps[i]) * (step_overhead + static_cast<double>(j - i));
      if (cost < best[j]) {
        best[j] = cost;
        begin_of[j] = i;
      }
    }
  }
  std::vector<size_t> ends;
  for (size_t j = n; j > 0; j = begin_of[j]) ends.insert(ends.begin(), j);
  return ends;
}

absl::StatusOr<std::vector<at::Tensor>> SdxlGenerator::generate(const std::vector<GenerationRequest>& requests) {
  notes_.clear();
  stage_seconds_.clear();
  counters_.clear();
  std::vector<at::Tensor> results(requests.size());
  // Requests of one size share batches, whatever their step counts (the pipeline starts each at its own step).
  std::map<std::pair<int64_t, int64_t>, std::vector<std::pair<int64_t, size_t>>> groups;  // (steps, request)
  const int64_t f = pipeline_->latent_factor();
  for (size_t i = 0; i < requests.size(); ++i) {
    const at::Tensor& rgb = requests[i].render_rgb;
    if (!rgb.defined() || rgb.dim() != 3 || rgb.size(2) != 3 || rgb.size(0) < 1 || rgb.size(1) < 1) {
      return absl::InvalidArgumentError(absl::StrCat("sdxl generate: request ", i, " render_rgb is not H x W x 3"));
    }
    if (pipeline_->controlnet()) {
      const at::Tensor& depth = requests[i].render_depth;
      const at::Tensor& alpha = requests[i].render_alpha;
      const auto hw = rgb.sizes().slice(0, 2);
      if (!depth.defined() || !alpha.defined() || depth.sizes() != hw || alpha.sizes() != hw) {
        return absl::InvalidArgumentError(absl::StrCat(
            "sdxl generate: request ", i, " needs render_depth and render_alpha of the render's size (ControlNet)"));
      }
      if (!std::isfinite(requests[i].control_scale)) {
        return absl::InvalidArgumentError(absl::StrCat("sdxl generate: request ", i, " control_scale is not finite"));
      }
    }
    if (!options_.inpaint.empty() &&
        (!requests[i].render_depth.defined() || requests[i].render_depth.sizes() != rgb.sizes().slice(0, 2))) {
      return absl::InvalidArgumentError(absl::StrCat(
          "sdxl generate: request ", i, " needs render_depth of the render's size (two-stage inpainting)"));
    }
    if (requests[i].ip_adapter_scale) {
      if (absl::Status range = check_ip_adapter_scale(*requests[i].ip_adapter_scale); !range.ok())
        return absl::InvalidArgumentError(absl::StrCat("sdxl generate: request ", i, " ", range.message()));
    }
    const double strength = requests[i].strength;
    if (!(strength >= 0.0 && strength <= 1.0)) {
      return absl::InvalidArgumentError(
          absl::StrCat("sdxl generate: request ", i, " strength ", strength, " outside [0, 1]"));
    }
    const auto run_steps = static_cast<int64_t>(options_.steps * strength);
    if (run_steps < 1) {
      results[i] = rgb.to(at::kFloat).clamp(0, 1).contiguous();
      continue;
    }
    groups[{rgb.size(0), rgb.size(1)}].push_back({run_steps, i});
  }
  const double step_overhead = !std::isnan(options_.batch_step_overhead) ? options_.batch_step_overhead
                               : pipeline_->device().is_cuda()           ? kImg2ImgStepOverheadCuda
                                                                         : 0.0;
  // The pipelines return CPU tensors, so the wall clock includes the device's work.
  const auto img2img_start = std::chrono::steady_clock::now();
  for (auto& [size, group] : groups) {
    const auto [height, width] = size;
    const int64_t padded_h = (height + f - 1) / f * f, padded_w = (width + f - 1) / f * f;
    // Most steps first, so that a batch's members start close together.
    std::stable_sort(group.begin(), group.end(), [](const auto& a, const auto& b) { return a.first > b.first; });
    std::vector<size_t> members;
    std::vector<int64_t> member_steps;
    for (const auto& [run_steps, index] : group) {
      members.push_back(index);
      member_steps.push_back(run_steps);
    }
    size_t begin = 0;
    for (const size_t end : img2img_batch_ends(member_steps, static_cast<size_t>(options_.batch_size), step_overhead)) {
      std::vector<at::Tensor> images, controls;
      std::vector<std::string> prompts;
      std::vector<uint64_t> seeds;
      std::vector<double> scales, ip_scales;
      std::vector<at::Tensor> references;
      for (size_t m = begin; m < end; ++m) {
        const GenerationRequest& r = requests[members[m]];
        at::Tensor chw = r.render_rgb.to(at::kFloat).clamp(0, 1).permute({2, 0, 1}).unsqueeze(0);
        const std::vector<int64_t> pad{0, padded_w - width, 0, padded_h - height};
        images.push_back(at::replication_pad2d(chw, pad));
        if (pipeline_->controlnet()) {
          GAPS_ASSIGN_OR_RETURN(DepthControl control,
                                depth_control_image(r.render_depth, r.render_alpha, options_.depth_control));
          controls.push_back(at::replication_pad2d(control.image.unsqueeze(0), pad));
          scales.push_back(r.control_scale);
        }
        prompts.push_back(r.prompt.empty() ? options_.prompt : r.prompt);
        seeds.push_back(r.seed);
        // IP-Adapter: the nearest ground-truth view is the image prompt (none for a request without one).
        if (!options_.ip_adapter.empty()) {
          references.push_back(r.references.empty() ? at::Tensor() : r.references[0].image);
          ip_scales.push_back(r.ip_adapter_scale.value_or(options_.ip_adapter_scale));
        }
      }
      sdxl::Img2ImgParams params;
      params.steps = options_.steps;
      params.guidance_scale = options_.guidance;
      params.reference_images = std::move(references);
      if (!ip_scales.empty()) params.ip_adapter_scales = std::move(ip_scales);
      for (size_t m = begin; m < end; ++m) params.strengths.push_back(requests[members[m]].strength);
      std::optional<sdxl::ControlInput> control;
      if (pipeline_->controlnet()) control = sdxl::ControlInput{at::cat(controls), scales};
      GAPS_ASSIGN_OR_RETURN(at::Tensor out, pipeline_->img2img(at::cat(images), prompts, params, seeds, control));
      for (size_t m = begin; m < end; ++m) {
        results[members[m]] =
            out[static_cast<int64_t>(m - begin)].slice(1, 0, height).slice(2, 0, width).permute({1, 2, 0}).contiguous();
        counters_["img2img_member_steps"] += static_cast<double>(member_steps[m]);
      }
      counters_["img2img_batches"] += 1;
      counters_["img2img_batch_steps"] += static_cast<double>((end - begin) * member_steps[begin]);
      begin = end;
    }
  }
  stage_seconds_["img2img"] = seconds_since(img2img_start);
  if (!options_.inpaint.empty()) {
    const auto inpaint_start = std::chrono::steady_clock::now();
    GAPS_RETURN_IF_ERROR(inpaint_uncovered(requests, results));
    // Loading SD2 on first need is its own stage (inpaint_pipeline()), not inpainting time.
    const auto load = stage_seconds_.find("inpaint_load");
    stage_seconds_["inpaint"] = seconds_since(inpaint_start) - (load == stage_seconds_.end() ? 0.0 : load->second);
  }
  if (options_.ip_adapter.empty()) {
    if (auto note =
            unapplied_ip_adapter_note("sdxl has no IP-Adapter loaded (options ip_adapter, image_encoder)", requests))
      notes_.push_back(*note);
  }
  return results;
}

absl::StatusOr<sdxl::InpaintPipeline*> SdxlGenerator::inpaint_pipeline() {
  if (inpaint_) return inpaint_.get();
  // dtype and device were checked by create().
  GAPS_ASSIGN_OR_RETURN(const at::ScalarType dtype, parse_dtype(options_.dtype));
  const auto load_start = std::chrono::steady_clock::now();
  auto pipeline = sdxl::InpaintPipeline::load(
      options_.inpaint,
      sdxl::InpaintPipelineOptions{dtype, at::Device(options_.device), options_.inpaint_scheduler, options_.variant});
  if (!pipeline.ok()) {
    return absl::Status(pipeline.status().code(),
                        absl::StrCat("sdxl backend: ", options_.inpaint,
                                     " is not a usable inpainting model: ", pipeline.status().message()));
  }
  inpaint_ = *std::move(pipeline);
  stage_seconds_["inpaint_load"] = seconds_since(load_start);
  return inpaint_.get();
}

absl::Status SdxlGenerator::inpaint_uncovered(const std::vector<GenerationRequest>& requests,
                                              std::vector<at::Tensor>& results) {
  for (size_t i = 0; i < requests.size(); ++i) {
    const GenerationRequest& r = requests[i];
    // The request's settings (the trainer's GapsConfig) when it carries them, else the options.
    const InpaintSettings settings =
        r.inpaint.value_or(InpaintSettings{options_.inpaint_depth_threshold, options_.inpaint_uncovered_fraction,
                                           static_cast<int>(options_.inpaint_dilation)});
    if (!std::isfinite(settings.depth_threshold)) {
      return absl::InvalidArgumentError(
          absl::StrCat("sdxl generate: request ", i,
                       " carries no inpaint settings and the inpaint_depth_threshold option (tau_d, "
                       "in render_depth's units) is not set"));
    }
    sdxl::TwoStageOptions two_stage;
    two_stage.depth_threshold = settings.depth_threshold;
    two_stage.min_uncovered_fraction = settings.uncovered_fraction;
    two_stage.dilation_kernel = settings.dilation;
    two_stage.inpaint.steps = options_.inpaint_steps;
    two_stage.inpaint.guidance_scale = options_.inpaint_guidance;
    GAPS_ASSIGN_OR_RETURN(
        sdxl::TwoStageResult out,
        sdxl::two_stage_generate(results[i].permute({2, 0, 1}).unsqueeze(0), r.render_depth.unsqueeze(0),
                                 {r.prompt.empty() ? options_.prompt : r.prompt}, {r.seed}, two_stage,
                                 [this] { return inpaint_pipeline(); }));
    results[i] = out.images[0].permute({1, 2, 0}).contiguous();
  }
  return absl::OkStatus();
}

}  // namespace gaps

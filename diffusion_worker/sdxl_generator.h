#pragma once
// The `sdxl` backend: pseudo-views by SDXL img2img of the render at each pose (diffusion_worker/sdxl),
// with the request's prompt (or the configured default), strength sigma(v) and seed; with a ControlNet,
// conditioned on the render's depth (depth_control.h) at the request's scale s_cn(v); with an IP-Adapter,
// the request's nearest reference view is the image prompt; with lora_steps > 0, adapt() trains LoRA
// adapters of the UNet on the ground-truth views (the paper's scene adaptation), frozen afterwards.
#include <memory>
#include <string>
#include <vector>

#include "absl/status/statusor.h"
#include "diffusion_worker/depth_control.h"
#include "diffusion_worker/sdxl/pipeline.h"
#include "gs_trainer/generator.h"

namespace gaps {

struct SdxlOptions {
  std::string weights;            // diffusers SDXL folder (required)
  int64_t steps = 30;             // steps of the full schedule; img2img runs int(steps * strength) of them
  double guidance = 5.0;          // classifier-free guidance scale
  std::string dtype = "float32";  // float32 | float16 | bfloat16 (half types need a CUDA device)
  std::string device = "cpu";     // cpu | cuda | cuda:N
  std::string prompt;             // used when a request has no prompt
  std::string scheduler;          // "" = the folder's; euler | ddim | dpmpp2m
  int64_t batch_size = 4;         // requests of one size and strength denoised together
  bool cuda_graphs = false;       // replay the UNet from CUDA graphs (CUDA device and build only)
  std::string variant;            // "" = full weight files; "fp16" = the *.fp16.safetensors copies
  // Depth ControlNet: a diffusers ControlNetModel folder ("" = the SDXL folder's "controlnet" component
  // if it lists one, else none) and the reliability mask of its depth image.
  std::string controlnet;
  DepthControlOptions depth_control;  // keys control_min_alpha, control_variance_window, control_max_relative_variance
  std::string ip_adapter;         // IP-Adapter weight file (diffusers single-file layout); "" = none
  std::string image_encoder;      // its CLIP image encoder folder (transformers); needed with ip_adapter
  double ip_adapter_scale = 0.5;  // lambda_ip, the scale of the image prompt's attention
  // Scene adaptation by LoRA (sdxl/lora_training.h): adapt() trains rank-lora_rank adapters (alpha =
  // rank) on to_q/to_k/to_v/to_out of every attention layer for lora_steps Adam steps at lora_lr
  // (0 steps = no training) and writes them to lora_save when set. lora: a LoRA file (diffusers/PEFT
  // safetensors) attached at startup instead, e.g. one saved by an earlier run.
  int64_t lora_steps = 0;
  int64_t lora_rank = 4;
  double lora_lr = 1e-4;
  std::string lora_save;
  std::string lora;
};

// JSON object with the keys above ("weights" required); unknown keys and bad values are errors.
absl::StatusOr<SdxlOptions> parse_sdxl_options(const std::string& json);

class SdxlGenerator final : public Generator {
 public:
  // Loads the whole model; an unusable folder is an error naming the problem.
  static absl::StatusOr<std::unique_ptr<SdxlGenerator>> create(const SdxlOptions& options);

  // "sdxl 1", or "sdxl 1 controlnet" when a ControlNet conditions the images.
  std::string name() const override;
  // Checks the views; with lora_steps > 0 trains the LoRA adapters on them (all views of one size,
  // padded as generate() pads renders; the prompt option as their prompt; with a ControlNet, each view's
  // render_depth / render_alpha give its control image at conditioning scale 1), replacing any earlier
  // adapters, and saves them to lora_save when set. An IP-Adapter cannot be loaded at the same time.
  absl::Status adapt(const std::vector<ReferenceView>& views) override;
  // Each render is padded at its bottom/right edge (replicated) to a multiple of the latent factor (8 for
  // SDXL: 504 x 378 runs at 504 x 384), run through img2img at its strength and cropped back. A strength
  // below one step of the schedule returns the render unchanged. With a ControlNet, each request's
  // render_depth / render_alpha give its control image (padded alike) and control_scale its scale.
  absl::StatusOr<std::vector<at::Tensor>> generate(const std::vector<GenerationRequest>& requests) override;

 private:
  SdxlGenerator(SdxlOptions options, std::unique_ptr<sdxl::SdxlPipeline> pipeline);
  absl::Status train_lora(const std::vector<ReferenceView>& views);
  SdxlOptions options_;
  std::unique_ptr<sdxl::SdxlPipeline> pipeline_;
};

}  // namespace gaps

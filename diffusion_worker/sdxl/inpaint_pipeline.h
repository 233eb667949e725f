#pragma once
// Stable Diffusion (2) inpainting as diffusers' StableDiffusionInpaintPipeline runs it with a 9-channel
// UNet (stabilityai/stable-diffusion-2-inpainting): one CLIP text encoder (last hidden state), the
// unconditional half of classifier-free guidance from the negative prompts (empty by default), the mask
// binarised at 0.5, the masked image (masked pixels set to 0 in [-1, 1]) encoded by the VAE, and at every
// step the UNet's input made of the scaled latents, the mask resized (nearest) to the latents and the
// masked-image latents. Strength 1 starts from pure noise; a lower strength noises the image's latents to
// its start step. The paper's second stage of generation (two_stage.h) regenerates uncovered regions with it.
#include <memory>
#include <optional>
#include <string>
#include <vector>

#include <ATen/Tensor.h>
#include "absl/status/statusor.h"
#include "diffusion_worker/sdxl/clip_text_encoder.h"
#include "diffusion_worker/sdxl/clip_tokenizer.h"
#include "diffusion_worker/sdxl/schedulers.h"
#include "diffusion_worker/sdxl/unet.h"
#include "diffusion_worker/sdxl/vae.h"

namespace gaps::sdxl {

struct InpaintPipelineOptions {
  at::ScalarType dtype = at::kFloat;  // of the UNet and text encoder; the VAE stays float32 when its config
                                      // asks for force_upcast
  at::Device device = at::kCPU;
  // "" = the folder's scheduler (the SD2 inpainting repository's is PNDM with skip_prk_steps); else
  // euler | ddim | dpmpp2m | pndm with the folder's scheduler config.
  std::string scheduler;
  std::string variant;  // weight files: "" or "fp16" (see PipelineOptions::variant)
};

struct InpaintParams {
  int64_t steps = 50;           // steps of the full schedule
  double strength = 1.0;        // 1 = from pure noise; else the last int(steps * strength) steps from the image
  double guidance_scale = 7.5;  // classifier-free guidance when > 1
  // The unconditional prompts of guidance: none (empty prompts), one for all images, or one per image.
  std::vector<std::string> negative_prompts;
};

class InpaintPipeline {
 public:
  // Loads unet (in_channels = 2 x latent channels + 1), vae, text_encoder, tokenizer and scheduler of a
  // diffusers folder; errors name the component and the problem.
  static absl::StatusOr<std::unique_ptr<InpaintPipeline>> load(const std::string& folder,
                                                               const InpaintPipelineOptions& options);

  // The text encoder's last hidden state, B x 77 x D.
  at::Tensor encode_prompts(const std::vector<std::string>& prompts) const;

  // images: B x 3 x H x W in [0, 1]; masks: B x 1 x H x W, regenerated where >= 0.5 (H, W multiples of the
  // latent factor); one prompt per image or one for all; seeds: one for the batch (diffusers' single
  // generator) or one per image (a generator list). Returns B x 3 x H x W in [0, 1], float32 on the CPU.
  absl::StatusOr<at::Tensor> inpaint(const at::Tensor& images, const at::Tensor& masks,
                                     const std::vector<std::string>& prompts, const InpaintParams& params,
                                     const std::vector<uint64_t>& seeds);

  const UNet2DCondition& unet() const { return *unet_; }
  const AutoencoderKL& vae() const { return *vae_; }
  int64_t latent_factor() const { return vae_->scale_factor(); }

 private:
  absl::Status check_inputs(const at::Tensor& images, const at::Tensor& masks, const std::vector<std::string>& prompts,
                            const InpaintParams& params, const std::vector<uint64_t>& seeds) const;
  // [uncond; cond] with guidance, else cond.
  at::Tensor prompt_context(const std::vector<std::string>& prompts, const InpaintParams& params, int64_t batch) const;

  InpaintPipelineOptions options_;
  SchedulerConfig scheduler_config_;
  std::optional<ClipTokenizer> tokenizer_;
  std::optional<ClipTextEncoder> text_encoder_;
  std::optional<UNet2DCondition> unet_;
  std::optional<AutoencoderKL> vae_;
};

}  // namespace gaps::sdxl

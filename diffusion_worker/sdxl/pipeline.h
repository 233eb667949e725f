#pragma once
// SDXL img2img as diffusers' StableDiffusionXLImg2ImgPipeline runs it: both text encoders (penultimate
// hidden states concatenated, pooled projection of the second), zero negative conditioning for
// classifier-free guidance (force_zeros_for_empty_prompt), VAE encoding of the input sampled from the
// latent distribution, noising to the strength's start step, denoising with text_time conditioning
// (original size = target size = the image's, crop (0, 0)), VAE decoding. With a ControlNet and a control
// image, as StableDiffusionXLControlNetImg2ImgPipeline without guess mode: the ControlNet sees the same
// batch as the UNet (both guidance halves, the control image repeated for each) and its residuals, times
// the conditioning scale, are added at every step (control_guidance_start 0, end 1).
// Optionally with IP-Adapter image prompts (ip_adapter.h): one reference image per image, encoded by CLIP
// and attended to by every cross-attention layer.
#include <memory>
#include <optional>
#include <string>
#include <vector>

#include <ATen/Tensor.h>
#include "absl/status/statusor.h"
#include "diffusion_worker/sdxl/clip_text_encoder.h"
#include "diffusion_worker/sdxl/clip_tokenizer.h"
#include "diffusion_worker/sdxl/clip_vision_encoder.h"
#include "diffusion_worker/sdxl/controlnet.h"
#include "diffusion_worker/sdxl/ip_adapter.h"
#include "diffusion_worker/sdxl/lora.h"
#include "diffusion_worker/sdxl/lora_training.h"
#include "diffusion_worker/sdxl/model_folder.h"
#include "diffusion_worker/sdxl/schedulers.h"
#include "diffusion_worker/sdxl/unet.h"
#include "diffusion_worker/sdxl/vae.h"

namespace gaps::sdxl {

struct PipelineOptions {
  at::ScalarType dtype = at::kFloat;  // of the UNet and text encoders; the VAE stays float32 when its
                                      // config asks for force_upcast (SDXL's VAE overflows in fp16)
  at::Device device = at::kCPU;
  std::string scheduler;  // "" = the folder's scheduler; else euler | ddim | dpmpp2m | pndm with its config
  // Capture the UNet's forward as a CUDA graph per input shape and replay it at every step (CUDA
  // devices in CUDA builds only; removes the per-kernel launch cost that dominates small images).
  bool cuda_graphs = false;
  // Weight files to read: "" = *.safetensors without a variant tag; "fp16" = *.fp16.safetensors (the
  // half-precision copies model repositories ship beside the full ones).
  std::string variant;
  // A diffusers ControlNetModel folder (config.json + weights, read with the same variant); "" = the
  // SDXL folder's "controlnet" component when model_index.json lists one, else no ControlNet.
  std::string controlnet;
  // IP-Adapter: its weight file (diffusers' single-file layout, e.g. ip-adapter_sdxl_vit-h.safetensors)
  // and the transformers folder of its CLIP image encoder (config.json, model.safetensors); both or
  // neither. With them, img2img takes reference images (Img2ImgParams::reference_images).
  std::string ip_adapter, image_encoder;
  // The VAE's type; unset: float32 when its config asks for force_upcast, else dtype. bfloat16 keeps float32's
  // exponent range (SDXL's VAE overflows float16's) at half the bytes; float16 suits VAEs made for it.
  std::optional<at::ScalarType> vae_dtype;
  // The UNet's, ControlNet's and VAE's convolution kernels (and so their activations) in channels-last order:
  // cuDNN's native layout for half-precision tensor cores, so no transposes around every convolution; on CUDA
  // their GroupNorms then run the fused channels-last kernel (cuda/group_norm_nhwc_cuda.h).
  bool channels_last = false;
};

struct UNetGraphs;  // the captured graphs (CUDA builds only)

struct Img2ImgParams {
  double strength = 0.5;  // fraction of the schedule re-run: steps from int(steps * strength) back
  // One strength per image instead (empty: `strength` for all). Each image runs exactly its own steps: an image
  // that starts later joins the batch's denoising when the schedule reaches its start step (its slot in the
  // batch is computed and discarded until then), so one batch serves mixed strengths and each image comes out
  // as it would alone.
  std::vector<double> strengths;
  int64_t steps = 30;           // steps of the full schedule
  double guidance_scale = 5.0;  // classifier-free guidance when > 1
  // IP-Adapter image prompts (pipelines loaded with one): per image a reference image H x W x 3 in [0, 1]
  // (an undefined tensor: none for that image), or empty for none at all; and the image attention's
  // scale, one for all images or one per image (0.5: the paper's lambda_ip). Images without a reference
  // get scale 0, which is plain img2img. The negative prompt of guidance is the projection of a zero
  // image embedding, as in diffusers.
  std::vector<at::Tensor> reference_images;
  std::vector<double> ip_adapter_scales = {0.5};
};

// The ControlNet input of one img2img call.
struct ControlInput {
  at::Tensor image;            // B x C x H x W (C = the ControlNet's conditioning channels), the images' size
  std::vector<double> scales;  // conditioning scale, one for all images or one per image
};

struct PromptEmbeddings {
  at::Tensor context;  // B x 77 x (D1 + D2)
  at::Tensor pooled;   // B x P
};

class SdxlPipeline {
 public:
  // Loads every component of a diffusers SDXL folder; any missing file, unsupported config or weight
  // mismatch is an error naming the component and the problem.
  static absl::StatusOr<std::unique_ptr<SdxlPipeline>> load(const std::string& folder, const PipelineOptions& options);

  PromptEmbeddings encode_prompts(const std::vector<std::string>& prompts) const;

  // images: B x 3 x H x W in [0, 1] (H, W multiples of the latent factor); one prompt per image (or one
  // for all). seeds: one seed for the whole batch (diffusers' single generator: latent draws for the
  // batch, then noise for the batch) or one per image (diffusers' generator list). Returns B x 3 x H x W
  // in [0, 1], float32 on the CPU.
  // control: the ControlNet's image and scale (an error when no ControlNet is loaded).
  absl::StatusOr<at::Tensor> img2img(const at::Tensor& images, const std::vector<std::string>& prompts,
                                     const Img2ImgParams& params, const std::vector<uint64_t>& seeds,
                                     const std::optional<ControlInput>& control = std::nullopt);

  // Scene adaptation: new LoRA adapters (config, seeded by options.seed) on the UNet, trained by
  // LoraTrainer on images (B x 3 x H x W in [0, 1], H and W multiples of the latent factor; their VAE
  // latents drawn with options.seed) with prompts (one, or one per image) and, with a ControlNet, control
  // (one scale for all images). The adapters replace any earlier LoRA; once trained they are frozen and
  // merged into the UNet's weights (UNetLora::merge_into), so generation runs at the base UNet's cost;
  // replacing them restores the base weights exactly.
  // Returns the loss of every step. With an IP-Adapter loaded, its image branch is off during training
  // (the adapters learn the text-conditioned UNet, as the paper trains them); img2img turns it back on.
  absl::StatusOr<std::vector<double>> train_lora(const at::Tensor& images, const std::vector<std::string>& prompts,
                                                 const std::optional<ControlInput>& control, const LoraConfig& config,
                                                 const LoraTrainingOptions& options);
  // Applies the adapters of a LoRA file (lora.h), merged as after train_lora, replacing any earlier LoRA.
  absl::Status load_lora(const std::string& path);
  // The same from a file's bytes (UNetLora::to_bytes of another pipeline); errors name `source`.
  absl::Status load_lora_bytes(std::string bytes, const std::string& source);
  // The applied LoRA (merged into the UNet); null when none.
  const UNetLora* lora() const { return lora_ ? &*lora_ : nullptr; }
  // Detaches the current LoRA, restoring the base UNet weights exactly, and drops captured UNet graphs
  // (they recorded the previous layers).
  absl::Status reset_lora();

  // Switches UNet graph capture and replay on or off (see PipelineOptions::cuda_graphs).
  absl::Status set_cuda_graphs(bool on);

  const UNet2DCondition& unet() const { return *unet_; }
  UNet2DCondition& unet() { return *unet_; }
  const AutoencoderKL& vae() const { return *vae_; }
  const ControlNet* controlnet() const { return controlnet_ ? &*controlnet_ : nullptr; }
  // The IP-Adapter and its image encoder; null without PipelineOptions::ip_adapter.
  const IpAdapter* ip_adapter() const { return ip_adapter_.get(); }
  const ClipVisionEncoder* image_encoder() const { return image_encoder_ ? &*image_encoder_ : nullptr; }
  int64_t latent_factor() const { return vae_->scale_factor(); }
  at::Device device() const { return options_.device; }

 private:
  // Makes `lora` the pipeline's, merged into the UNet (reset_lora has run).
  absl::Status apply_lora(UNetLora lora);
  PipelineOptions options_;
  SchedulerConfig scheduler_config_;
  bool force_zeros_for_empty_prompt_ = true;
  std::optional<ClipTokenizer> tokenizer_, tokenizer_2_;
  std::optional<ClipTextEncoder> text_encoder_, text_encoder_2_;
  std::optional<UNet2DCondition> unet_;
  std::optional<AutoencoderKL> vae_;
  std::optional<ControlNet> controlnet_;
  std::shared_ptr<UNetGraphs> graphs_;  // set while graph replay is on
  std::optional<ClipVisionEncoder> image_encoder_;
  std::unique_ptr<IpAdapter> ip_adapter_;
  std::optional<UNetLora> lora_;
  // Host copies of the adapted projections' base weights, made at the first merge and kept for every later one
  // (a worker switching scenes merges and unmerges their adapters at every switch).
  UNetLora::BaseCopies lora_base_copies_;

  absl::Status load_ip_adapter(at::TensorOptions model_options);
  // Encodes and projects the reference images and hands them to the UNet's decoupled cross-attention
  // (negative prompts first when guidance doubles the batch).
  absl::Status set_image_prompts(const Img2ImgParams& params, int64_t batch);

  at::Tensor run_unet(const UNetInputs& in);
  absl::Status load_controlnet(const ModelFolder& folder);
  // The type and device of the models with convolutions, and their kernels' memory format (channels_last).
  at::TensorOptions convolution_options() const;
  absl::Status check_control(const ControlInput& control, const at::Tensor& images) const;
  // The images of a batch that start the schedule at one step, with a scheduler of their own: a multistep
  // scheduler's history (DPM-Solver++, PNDM) belongs to the images that took those steps.
  struct Cohort {
    int64_t start = 0;
    std::unique_ptr<Scheduler> scheduler;
    std::vector<int64_t> rows;  // the images' indices in the batch
  };
  absl::StatusOr<std::vector<Cohort>> make_cohorts(const Img2ImgParams& params, int64_t batch) const;
  // The schedule from the earliest cohort's start, from noised latents, with classifier-free guidance when > 1;
  // each step advances the cohorts that have started.
  at::Tensor denoise(std::vector<Cohort>& cohorts, at::Tensor latents, const std::vector<std::string>& prompts,
                     int64_t height, int64_t width, double guidance_scale, const std::optional<ControlInput>& control);
};

}  // namespace gaps::sdxl

#pragma once
// The `sdxl` backend: pseudo-views by SDXL img2img of the render at each pose (diffusion_worker/sdxl),
// with the request's prompt (or the configured default), strength sigma(v) and seed; with a ControlNet,
// conditioned on the render's depth (depth_control.h) at the request's scale s_cn(v); with an IP-Adapter,
// the request's nearest reference view is the image prompt. LoRA comes with the other conditioning backends.
#include <limits>
#include <memory>
#include <string>
#include <vector>

#include "absl/status/statusor.h"
#include "diffusion_worker/depth_control.h"
#include "diffusion_worker/sdxl/inpaint_pipeline.h"
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
  // Two-stage generation (eq. two_stage, sdxl/two_stage.h): an SD2 inpainting folder ("" = off), loaded on
  // first need, regenerates the pixels whose render_depth is below inpaint_depth_threshold (tau_d; required
  // with inpaint), dilated 15 x 15, in views more than 2% uncovered.
  std::string inpaint;
  double inpaint_depth_threshold = std::numeric_limits<double>::quiet_NaN();
  std::string inpaint_scheduler;  // "" = the folder's; euler | ddim | dpmpp2m (SD2's PNDM is not implemented)
  int64_t inpaint_steps = 30;     // the second stage runs from pure noise (strength 1)
  double inpaint_guidance = 7.5;
  double inpaint_uncovered_fraction = 0.02;  // inpaint views with more uncovered pixels than this
  int64_t inpaint_dilation = 15;             // side of the square dilation kernel (odd)
};

// JSON object with the keys above ("weights" required); unknown keys and bad values are errors.
absl::StatusOr<SdxlOptions> parse_sdxl_options(const std::string& json);

class SdxlGenerator final : public Generator {
 public:
  // Loads the whole model; an unusable folder is an error naming the problem.
  static absl::StatusOr<std::unique_ptr<SdxlGenerator>> create(const SdxlOptions& options);

  // "sdxl 1", or "sdxl 1 controlnet" when a ControlNet conditions the images.
  std::string name() const override;
  // Learns nothing yet (per-scene LoRA comes with the conditioning backends): checks the views only.
  absl::Status adapt(const std::vector<ReferenceView>& views) override;
  // Each render is padded at its bottom/right edge (replicated) to a multiple of the latent factor (8 for
  // SDXL: 504 x 378 runs at 504 x 384), run through img2img at its strength and cropped back. A strength
  // below one step of the schedule returns the render unchanged. With a ControlNet, each request's
  // render_depth / render_alpha give its control image (padded alike) and control_scale its scale.
  // With `inpaint`, each result then goes through the two-stage pass (render_depth required).
  absl::StatusOr<std::vector<at::Tensor>> generate(const std::vector<GenerationRequest>& requests) override;

 private:
  SdxlGenerator(SdxlOptions options, std::unique_ptr<sdxl::SdxlPipeline> pipeline);
  SdxlOptions options_;
  std::unique_ptr<sdxl::SdxlPipeline> pipeline_;
  // Two-stage generation: the inpainting pipeline (loaded on first call) and its pass over the results.
  absl::StatusOr<sdxl::InpaintPipeline*> inpaint_pipeline();
  absl::Status inpaint_uncovered(const std::vector<GenerationRequest>& requests, std::vector<at::Tensor>& results);
  std::unique_ptr<sdxl::InpaintPipeline> inpaint_;
};

}  // namespace gaps

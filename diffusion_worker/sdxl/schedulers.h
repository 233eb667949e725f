#pragma once
// The noise schedulers of diffusers that SDXL pipelines use: Euler discrete (SDXL's default), DDIM
// (eta 0), DPM-Solver++ (2M, midpoint) and PNDM with skip_prk_steps (PLMS; Stable Diffusion 2's), with diffusers'
// timestep spacings ("leading", "trailing", "linspace"), epsilon prediction, and the noising of img2img's start
// latents.
//
// Steps are addressed by index into timesteps() (not by timestep value), so img2img starts at an index.
#include <memory>
#include <string>
#include <vector>

#include <ATen/Tensor.h>
#include <nlohmann/json.hpp>
#include "absl/status/statusor.h"

namespace gaps::sdxl {

struct SchedulerConfig {
  std::string kind = "euler";  // "euler" | "ddim" | "dpmpp2m" | "pndm"
  int64_t num_train_timesteps = 1000, steps_offset = 1;
  double beta_start = 0.00085, beta_end = 0.012;
  std::string beta_schedule = "scaled_linear";  // or "linear"
  std::string timestep_spacing = "leading";     // "leading" | "trailing" | "linspace"
  bool clip_sample = false;                     // DDIM only
  bool set_alpha_to_one = false;                // DDIM and PNDM: the last step's target
  // From a diffusers scheduler_config.json; its _class_name picks the kind unless kind_override is set.
  // Options this implementation lacks (Karras sigmas, v-prediction, thresholding, ...) are an error.
  static absl::StatusOr<SchedulerConfig> from_json(const nlohmann::json& config, const std::string& kind_override = "");
};

class Scheduler {
 public:
  virtual ~Scheduler() = default;
  // Prepares num_inference_steps steps (and resets any multistep history).
  virtual void set_timesteps(int64_t num_inference_steps) = 0;
  // The UNet's timestep at each step, first to last.
  const std::vector<float>& timesteps() const { return timesteps_; }
  // Scale of pure noise at the first step (latents for text-to-image are N(0, 1) times this).
  virtual double init_noise_sigma() const { return 1.0; }
  // The UNet's input at step index (identity except for Euler).
  virtual at::Tensor scale_model_input(const at::Tensor& sample, int64_t index) const { return sample; }
  // The sample after step index, from the model's noise prediction. Steps run consecutively from any
  // start (img2img starts part-way).
  virtual at::Tensor step(const at::Tensor& model_output, int64_t index, const at::Tensor& sample) = 0;
  // Clean latents noised to the level of step index (img2img's start).
  virtual at::Tensor add_noise(const at::Tensor& original, const at::Tensor& noise, int64_t index) const = 0;
  // The training schedule's cumulative alpha products (float32, num_train_timesteps; DDPM noising).
  const at::Tensor& alphas_cumprod() const { return alphas_cumprod_; }

 protected:
  explicit Scheduler(const SchedulerConfig& config);
  // diffusers' spaced timesteps for n steps (as float; integer-valued except Euler's linspace).
  std::vector<double> spaced_timesteps(int64_t n, bool one_extra_for_dpm) const;

  SchedulerConfig config_;
  at::Tensor alphas_cumprod_;  // float32, num_train_timesteps
  std::vector<float> timesteps_;
};

absl::StatusOr<std::unique_ptr<Scheduler>> make_scheduler(const SchedulerConfig& config);

// Classifier-free guidance: uncond + scale (cond - uncond), from a batch stacked [uncond; cond].
at::Tensor classifier_free_guidance(const at::Tensor& stacked_prediction, double guidance_scale);

}  // namespace gaps::sdxl

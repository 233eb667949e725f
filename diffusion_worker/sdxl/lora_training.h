#pragma once
// Scene adaptation of the UNet by LoRA: the adapters of a UNetLora are trained with the denoising loss
//   L = mean || eps - eps_theta(x_t, t, c, control) ||^2,  x_t = sqrt(abar_t) x0 + sqrt(1 - abar_t) eps
// on the VAE latents x0 of the ground-truth views (t uniform over the training timesteps, eps ~ N(0, 1)
// from a seeded generator), optionally with a ControlNet's residuals of the views' control images (depth),
// by Adam on the adapters alone (the UNet's and ControlNet's weights get no gradients). Autograd runs on
// the UNet's ATen ops, so training needs weights that are not inference tensors and no InferenceMode.
#include <vector>

#include <ATen/Tensor.h>
#include "absl/status/statusor.h"
#include "diffusion_worker/sdxl/controlnet.h"
#include "diffusion_worker/sdxl/lora.h"
#include "diffusion_worker/sdxl/unet.h"

namespace gaps::sdxl {

struct LoraTrainingOptions {
  int64_t steps = 50;
  double learning_rate = 1e-4;
  double beta1 = 0.9, beta2 = 0.999, epsilon = 1e-8;  // Adam (torch.optim.Adam's defaults)
  uint64_t seed = 0;                                  // draws of timesteps and noise
  // Replay every step after the first two from one captured CUDA graph of the loss and its backward (the
  // Adam update stays eager). SDXL's step is thousands of small launches and the host cannot issue them as
  // fast as an H200 runs them; replayed, the step costs what its kernels cost. Needs the views on a CUDA
  // device and a CUDA build; the draws, losses and updates are those of the eager steps.
  bool cuda_graph = false;
};

// The ground-truth views, one batch entry each.
struct LoraTrainingData {
  at::Tensor latents;                // N x C x h x w: VAE latents times the VAE's scaling factor
  at::Tensor encoder_hidden_states;  // N x T x cross_attention_dim
  at::Tensor text_embeds, time_ids;  // N x P and N x 6 ("text_time" conditioning)
  at::Tensor control_images;         // N x 3 x H x W for the ControlNet; undefined = no control
  double conditioning_scale = 1.0;
};

// The noise and timesteps of one loss evaluation, one per view.
struct DenoisingSample {
  at::Tensor noise;      // like the latents
  at::Tensor timesteps;  // N, integer-valued, in [0, num_train_timesteps)
};

class LoraTrainer {
 public:
  // Trains lora's adapters (attached to unet) while the trainer lives: they require gradients from
  // construction and are frozen again on destruction. alphas_cumprod: the training noise schedule
  // (Scheduler::alphas_cumprod). controlnet (may be null) must outlive the trainer.
  LoraTrainer(UNet2DCondition& unet, const UNetLora& lora, at::Tensor alphas_cumprod, const ControlNet* controlnet,
              LoraTrainingOptions options);
  ~LoraTrainer();
  LoraTrainer(const LoraTrainer&) = delete;
  LoraTrainer& operator=(const LoraTrainer&) = delete;

  // The denoising loss of data at sample, differentiable with respect to the adapters.
  absl::StatusOr<at::Tensor> loss(const LoraTrainingData& data, const DenoisingSample& sample) const;
  // One Adam step on the loss at sample; returns the loss before the step.
  absl::StatusOr<double> step(const LoraTrainingData& data, const DenoisingSample& sample);
  // Noise and timesteps for every view from the trainer's generator.
  DenoisingSample draw(const LoraTrainingData& data);
  // options.steps steps, each on a fresh draw over all views; the loss of every step.
  absl::StatusOr<std::vector<double>> train(const LoraTrainingData& data);

 private:
  absl::Status check(const LoraTrainingData& data) const;
  // The loss at sample with the adapters' gradients of it accumulated (they start undefined).
  absl::StatusOr<at::Tensor> loss_and_gradients(const LoraTrainingData& data, const DenoisingSample& sample);
  // Adam on the adapters that have gradients.
  void adam_update();
  // count eager steps, each on a fresh draw; their losses appended to losses.
  absl::Status eager_steps(const LoraTrainingData& data, int64_t count, std::vector<double>* losses);
  absl::StatusOr<std::vector<double>> train_with_cuda_graph(const LoraTrainingData& data);

  UNet2DCondition& unet_;
  std::vector<at::Tensor> parameters_;
  std::vector<at::Tensor> first_moments_, second_moments_;
  int64_t adam_steps_ = 0;
  at::Tensor alphas_cumprod_;
  const ControlNet* controlnet_;
  LoraTrainingOptions options_;
  at::Generator generator_;
};

}  // namespace gaps::sdxl

#include "diffusion_worker/sdxl/lora_training.h"

#include <algorithm>
#include <cmath>
#include <string>
#include <utility>

#include <ATen/ATen.h>
#include <ATen/CPUGeneratorImpl.h>
#include <ATen/core/grad_mode.h>
#include <ATen/ops/_foreach_add.h>
#include <ATen/ops/_foreach_addcdiv.h>
#include <ATen/ops/_foreach_addcmul.h>
#include <ATen/ops/_foreach_div.h>
#include <ATen/ops/_foreach_mul.h>
#include <ATen/ops/_foreach_sqrt.h>
#include <c10/core/InferenceMode.h>
#include <c10/util/Exception.h>
#include "absl/strings/str_cat.h"
#include "absl/strings/str_join.h"

#if defined(GAPS_CUDA_KERNELS)
#include <ATen/cuda/CUDAGraph.h>
#include <c10/cuda/CUDACachingAllocator.h>
#include "diffusion_worker/sdxl/side_stream.h"
#endif

namespace gaps::sdxl {
namespace {

std::string shape_text(const at::Tensor& t) {
  return t.defined() ? absl::StrCat("[", absl::StrJoin(t.sizes(), ", "), "]") : "undefined";
}

}  // namespace

LoraTrainer::LoraTrainer(UNet2DCondition& unet, const UNetLora& lora, at::Tensor alphas_cumprod,
                         const ControlNet* controlnet, LoraTrainingOptions options)
    : unet_(unet),
      parameters_(lora.parameters()),
      alphas_cumprod_(std::move(alphas_cumprod)),
      controlnet_(controlnet),
      options_(options),
      generator_(at::make_generator<at::CPUGeneratorImpl>(options.seed)) {
  for (auto& p : parameters_) {
    p.set_requires_grad(true);
    first_moments_.push_back(at::zeros_like(p));
    second_moments_.push_back(at::zeros_like(p));
  }
}

LoraTrainer::~LoraTrainer() {
  for (auto& p : parameters_) {
    p.mutable_grad() = at::Tensor();
    p.set_requires_grad(false);
  }
}

absl::Status LoraTrainer::check(const LoraTrainingData& data) const {
  if (c10::InferenceMode::is_enabled()) {
    return absl::FailedPreconditionError("LoRA training cannot run inside InferenceMode (it needs autograd)");
  }
  if (!data.latents.defined() || data.latents.dim() != 4) {
    return absl::InvalidArgumentError(
        absl::StrCat("LoRA training: latents must be N x C x h x w, got ", shape_text(data.latents)));
  }
  const int64_t n = data.latents.size(0);
  for (const auto& [name, t] :
       {std::pair<const char*, const at::Tensor&>{"encoder_hidden_states", data.encoder_hidden_states},
        {"text_embeds", data.text_embeds},
        {"time_ids", data.time_ids}}) {
    if (!t.defined() || t.size(0) != n) {
      return absl::InvalidArgumentError(
          absl::StrCat("LoRA training: ", name, " needs one entry per view (", n, "), got ", shape_text(t)));
    }
  }
  if (data.control_images.defined() && controlnet_ == nullptr) {
    return absl::InvalidArgumentError("LoRA training: control images given but no ControlNet");
  }
  if (controlnet_ != nullptr && (!data.control_images.defined() || data.control_images.size(0) != n)) {
    return absl::InvalidArgumentError(absl::StrCat("LoRA training with a ControlNet needs one control image per view (",
                                                   n, "), got ", shape_text(data.control_images)));
  }
  return absl::OkStatus();
}

absl::StatusOr<at::Tensor> LoraTrainer::loss(const LoraTrainingData& data, const DenoisingSample& sample) const {
  if (absl::Status s = check(data); !s.ok()) return s;
  if (!sample.noise.defined() || !sample.noise.sizes().equals(data.latents.sizes()) || !sample.timesteps.defined() ||
      sample.timesteps.numel() != data.latents.size(0)) {
    return absl::InvalidArgumentError(absl::StrCat("LoRA training: noise ", shape_text(sample.noise), " and timesteps ",
                                                   shape_text(sample.timesteps), " must match the latents ",
                                                   shape_text(data.latents)));
  }
  at::AutoGradMode grad_mode(true);
  try {
    const at::Tensor x0 = data.latents, noise = sample.noise.to(x0.options());
    const at::Tensor t = sample.timesteps.to(at::kLong).to(alphas_cumprod_.device());
    const at::Tensor abar = alphas_cumprod_.index_select(0, t).to(x0.options()).view({-1, 1, 1, 1});
    UNetInputs in;
    in.sample = abar.sqrt() * x0 + (1 - abar).sqrt() * noise;
    in.timestep = t.to(x0.options());
    in.encoder_hidden_states = data.encoder_hidden_states;
    in.text_embeds = data.text_embeds;
    in.time_ids = data.time_ids;
    if (controlnet_ != nullptr) {
      at::NoGradGuard frozen;
      ControlNetResiduals residuals =
          controlnet_->forward(in, data.control_images, at::full({1}, data.conditioning_scale, x0.options()));
      in.down_block_residuals = std::move(residuals.down);
      in.mid_block_residual = std::move(residuals.mid);
    }
    return (unet_.forward(in).to(at::kFloat) - noise.to(at::kFloat)).pow(2).mean();
  } catch (const c10::Error& e) {
    return absl::InternalError(absl::StrCat("LoRA training loss failed: ", e.what_without_backtrace()));
  }
}

absl::StatusOr<at::Tensor> LoraTrainer::loss_and_gradients(const LoraTrainingData& data,
                                                           const DenoisingSample& sample) {
  for (auto& p : parameters_) p.mutable_grad() = at::Tensor();
  auto value = loss(data, sample);
  if (!value.ok()) return value.status();
  try {
    value->backward();
  } catch (const c10::Error& e) {
    return absl::InternalError(
        absl::StrCat("LoRA training backward failed (inference-mode weights?): ", e.what_without_backtrace()));
  }
  return value;
}

// torch.optim.Adam's update, on the adapters only, as multi-tensor operations: SDXL has 560 adapter tensors,
// and eight launches for each would cost more than the arithmetic (the same element-wise operations in the
// same order as the per-tensor update, so the same numbers).
void LoraTrainer::adam_update() {
  at::NoGradGuard no_grad;
  ++adam_steps_;
  std::vector<at::Tensor> parameters, gradients, first_moments, second_moments;
  for (size_t i = 0; i < parameters_.size(); ++i) {
    if (!parameters_[i].grad().defined()) continue;
    parameters.push_back(parameters_[i]);
    gradients.push_back(parameters_[i].grad());
    first_moments.push_back(first_moments_[i]);
    second_moments.push_back(second_moments_[i]);
  }
  if (parameters.empty()) return;
  const double correction1 = 1 - std::pow(options_.beta1, adam_steps_);
  const double correction2 = 1 - std::pow(options_.beta2, adam_steps_);
  at::_foreach_mul_(first_moments, options_.beta1);
  at::_foreach_add_(first_moments, gradients, 1 - options_.beta1);
  at::_foreach_mul_(second_moments, options_.beta2);
  at::_foreach_addcmul_(second_moments, gradients, gradients, 1 - options_.beta2);
  std::vector<at::Tensor> denominators = at::_foreach_sqrt(second_moments);
  at::_foreach_div_(denominators, std::sqrt(correction2));
  at::_foreach_add_(denominators, options_.epsilon);
  at::_foreach_addcdiv_(parameters, first_moments, denominators, -options_.learning_rate / correction1);
}

absl::StatusOr<double> LoraTrainer::step(const LoraTrainingData& data, const DenoisingSample& sample) {
  auto value = loss_and_gradients(data, sample);
  if (!value.ok()) return value.status();
  adam_update();
  return value->item<double>();
}

DenoisingSample LoraTrainer::draw(const LoraTrainingData& data) {
  const at::Tensor noise = at::randn(data.latents.sizes(), generator_, at::TensorOptions().dtype(at::kFloat));
  const at::Tensor timesteps =
      at::randint(0, alphas_cumprod_.size(0), {data.latents.size(0)}, generator_, at::TensorOptions().dtype(at::kLong));
  return {noise.to(data.latents.options()), timesteps};
}

absl::StatusOr<std::vector<double>> LoraTrainer::train(const LoraTrainingData& data) {
  if (absl::Status s = check(data); !s.ok()) return s;
  if (options_.cuda_graph) return train_with_cuda_graph(data);
  std::vector<double> losses;
  if (absl::Status s = eager_steps(data, options_.steps, &losses); !s.ok()) return s;
  return losses;
}

absl::Status LoraTrainer::eager_steps(const LoraTrainingData& data, int64_t count, std::vector<double>* losses) {
  for (int64_t i = 0; i < count; ++i) {
    auto value = step(data, draw(data));
    if (!value.ok()) return value.status();
    losses->push_back(*value);
  }
  return absl::OkStatus();
}

#if defined(GAPS_CUDA_KERNELS)
absl::StatusOr<std::vector<double>> LoraTrainer::train_with_cuda_graph(const LoraTrainingData& data) {
  if (!data.latents.is_cuda()) {
    return absl::InvalidArgumentError(absl::StrCat("LoRA training: a CUDA graph needs the views on a CUDA device, not ",
                                                   data.latents.device().str()));
  }
  // The first steps run eagerly: they are real steps, and they let cuBLAS, cuDNN and the allocator settle
  // before the capture, which must not allocate workspaces or choose algorithms.
  constexpr int64_t kEagerSteps = 2;
  // Whatever way this returns, the caller's stream waits for the work issued here (the views it owns are read).
  const SideStream side(data.latents.device().index());
  const c10::cuda::CUDAStream& stream = side.stream();
  std::vector<double> losses;
  if (absl::Status s = eager_steps(data, std::min(kEagerSteps, options_.steps), &losses); !s.ok()) return s;
  if (options_.steps > kEagerSteps) {
    // The graph reads its noise and timesteps from these buffers, refilled before every replay, and leaves
    // the loss and the adapters' gradients in tensors of its own memory pool.
    DenoisingSample buffers = draw(data);  // its noise is already on the views' device
    buffers.timesteps = buffers.timesteps.to(data.latents.device());
    for (auto& p : parameters_) p.mutable_grad() = at::Tensor();
    // The eager steps' cached blocks go back to the device, so that the graph's private pool can take their
    // place (the capture itself must not need to free memory, under a memory cap least of all).
    stream.synchronize();
    c10::cuda::CUDACachingAllocator::emptyCache();
    at::cuda::CUDAGraph graph;
    absl::StatusOr<at::Tensor> loss = absl::UnknownError("not captured");
    std::string capture_error;
    try {
      // Thread-local: the process's other threads may keep using the device meanwhile.
      graph.capture_begin(at::cuda::MempoolId_t{0, 0}, cudaStreamCaptureModeThreadLocal);
      loss = loss_and_gradients(data, buffers);  // its errors come back as statuses
      graph.capture_end();                       // also ends a capture that an error invalidated
    } catch (const c10::Error& e) {
      capture_error = e.what_without_backtrace();
    }
    if (!loss.ok() || !capture_error.empty()) {
      for (auto& p : parameters_) p.mutable_grad() = at::Tensor();
      return absl::InternalError(
          absl::StrCat("LoRA training: capturing the step as a CUDA graph failed (train without "
                       "it: lora_cuda_graph false): ",
                       loss.ok() ? capture_error : loss.status().message()));
    }
    for (int64_t i = kEagerSteps; i < options_.steps; ++i) {
      if (i > kEagerSteps) {
        const DenoisingSample sample = draw(data);
        buffers.noise.copy_(sample.noise);
        buffers.timesteps.copy_(sample.timesteps);
      }
      graph.replay();
      adam_update();
      losses.push_back(loss->item<double>());
    }
    // The gradients live in the graph's pool, which goes with it.
    for (auto& p : parameters_) p.mutable_grad() = at::Tensor();
  }
  return losses;
}
#else
absl::StatusOr<std::vector<double>> LoraTrainer::train_with_cuda_graph(const LoraTrainingData&) {
  return absl::UnimplementedError("LoRA training: CUDA graphs need a CUDA build of gaps");
}
#endif

}  // namespace gaps::sdxl

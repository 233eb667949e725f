#include "diffusion_worker/sdxl/schedulers.h"

#include <algorithm>
#include <cmath>

#include <ATen/ATen.h>
#include "absl/strings/str_cat.h"
#include "common/status_macros.h"
#include "diffusion_worker/sdxl/model_folder.h"

namespace gaps::sdxl {
namespace {

// sigma of every training timestep, sqrt((1 - abar) / abar), computed in float32 like diffusers.
std::vector<double> training_sigmas(const at::Tensor& alphas_cumprod) {
  const at::Tensor s = ((1 - alphas_cumprod) / alphas_cumprod).pow(0.5).contiguous();
  return std::vector<double>(s.data_ptr<float>(), s.data_ptr<float>() + s.numel());
}

// numpy.interp over integer abscissae 0..n-1.
double interpolate(const std::vector<double>& values, double t) {
  if (t <= 0) return values.front();
  if (t >= static_cast<double>(values.size() - 1)) return values.back();
  const auto i = static_cast<size_t>(std::floor(t));
  const double slope = values[i + 1] - values[i];
  return slope * (t - static_cast<double>(i)) + values[i];
}

float abar_at(const at::Tensor& alphas_cumprod, int64_t t) { return alphas_cumprod.data_ptr<float>()[t]; }

class EulerDiscrete final : public Scheduler {
 public:
  explicit EulerDiscrete(const SchedulerConfig& c) : Scheduler(c) {}
  void set_timesteps(int64_t n) override {
    const std::vector<double> train = training_sigmas(alphas_cumprod_);
    timesteps_.clear();
    sigmas_.clear();
    for (double t : spaced_timesteps(n, false)) {
      timesteps_.push_back(static_cast<float>(t));
      sigmas_.push_back(static_cast<float>(interpolate(train, static_cast<float>(t))));
    }
    sigmas_.push_back(0.0f);
  }
  double init_noise_sigma() const override {
    const double max_sigma = *std::max_element(sigmas_.begin(), sigmas_.end());
    return config_.timestep_spacing == "leading" ? std::sqrt(max_sigma * max_sigma + 1) : max_sigma;
  }
  at::Tensor scale_model_input(const at::Tensor& sample, int64_t i) const override {
    const float s = sigmas_.at(i);
    return sample / std::sqrt(s * s + 1.0f);
  }
  at::Tensor step(const at::Tensor& eps, int64_t i, const at::Tensor& sample) override {
    const at::Tensor x = sample.to(at::kFloat);
    const float sigma = sigmas_.at(i);
    const at::Tensor x0 = x - sigma * eps;
    const at::Tensor derivative = (x - x0) / sigma;
    return (x + derivative * (sigmas_.at(i + 1) - sigma)).to(eps.scalar_type());
  }
  at::Tensor add_noise(const at::Tensor& original, const at::Tensor& noise, int64_t i) const override {
    return original + noise * sigmas_.at(i);
  }

 private:
  std::vector<float> sigmas_;
};

// Schedulers that step between integer training timesteps num_train_timesteps / n apart and noise img2img's
// start as DDPM does (DDIM, PNDM).
class TimestepScheduler : public Scheduler {
 public:
  using Scheduler::Scheduler;
  at::Tensor add_noise(const at::Tensor& original, const at::Tensor& noise, int64_t i) const override {
    const float abar = abar_at(alphas_cumprod_, static_cast<int64_t>(timesteps_.at(i)));
    return std::pow(abar, 0.5f) * original + std::pow(1.0f - abar, 0.5f) * noise;
  }

 protected:
  // diffusers' spaced timesteps for n steps, rounded; and the stride between them.
  void set_integer_timesteps(int64_t n) {
    timesteps_.clear();
    for (double t : spaced_timesteps(n, false)) timesteps_.push_back(static_cast<float>(std::llround(t)));
    stride_ = config_.num_train_timesteps / n;
  }
  // abar at the step's target timestep prev; below 0 (the last step) 1 or abar_0 by set_alpha_to_one.
  float abar_target(int64_t prev) const {
    if (prev >= 0) return abar_at(alphas_cumprod_, prev);
    return config_.set_alpha_to_one ? 1.0f : abar_at(alphas_cumprod_, 0);
  }
  int64_t stride_ = 1;
};

class Ddim final : public TimestepScheduler {
 public:
  explicit Ddim(const SchedulerConfig& c) : TimestepScheduler(c) {}
  void set_timesteps(int64_t n) override { set_integer_timesteps(n); }
  at::Tensor step(const at::Tensor& eps, int64_t i, const at::Tensor& sample) override {
    const auto t = static_cast<int64_t>(timesteps_.at(i));
    const float abar = abar_at(alphas_cumprod_, t);
    const float abar_prev = abar_target(t - stride_);
    at::Tensor x0 = (sample - std::pow(1.0f - abar, 0.5f) * eps) / std::pow(abar, 0.5f);
    if (config_.clip_sample) x0 = x0.clamp(-1.0, 1.0);
    return std::pow(abar_prev, 0.5f) * x0 + std::pow(1.0f - abar_prev, 0.5f) * eps;
  }
};

// DPM-Solver++ in data (x0) prediction, order 2, midpoint; first order at the first and last step.
class DpmSolverPP2M final : public Scheduler {
 public:
  explicit DpmSolverPP2M(const SchedulerConfig& c) : Scheduler(c) {}
  void set_timesteps(int64_t n) override {
    const std::vector<double> train = training_sigmas(alphas_cumprod_);
    timesteps_.clear();
    sigmas_.clear();
    for (double t : spaced_timesteps(n, true)) {
      timesteps_.push_back(static_cast<float>(std::llround(t)));
      sigmas_.push_back(static_cast<float>(interpolate(train, std::llround(t))));
    }
    sigmas_.push_back(0.0f);
    previous_x0_ = at::Tensor();
    next_index_ = -1;
  }
  at::Tensor step(const at::Tensor& eps, int64_t i, const at::Tensor& sample) override {
    // Any start (img2img starts part-way), then consecutive steps: the history belongs to the last one.
    TORCH_CHECK(next_index_ < 0 || i == next_index_, "DPM-Solver++ steps must run in order: expected step ",
                next_index_, ", got ", i);
    const at::Tensor x = sample.to(at::kFloat);
    const Level s0 = level(sigmas_.at(i)), t = level(sigmas_.at(i + 1));
    const at::Tensor x0 = (x - s0.sigma * eps.to(at::kFloat)) / s0.alpha;
    const float h = t.lambda - s0.lambda;
    const float decay = t.alpha * (std::exp(-h) - 1.0f);
    at::Tensor out = (t.sigma / s0.sigma) * x - decay * x0;
    const bool last = i + 1 == static_cast<int64_t>(timesteps_.size());
    if (previous_x0_.defined() && !last) {
      const Level s1 = level(sigmas_.at(i - 1));
      const float r0 = (s0.lambda - s1.lambda) / h;
      out = out - 0.5f * decay * ((1.0f / r0) * (x0 - previous_x0_));
    }
    previous_x0_ = x0;
    next_index_ = i + 1;
    return out.to(eps.scalar_type());
  }
  at::Tensor add_noise(const at::Tensor& original, const at::Tensor& noise, int64_t i) const override {
    const Level l = level(sigmas_.at(i));
    return l.alpha * original + l.sigma * noise;
  }

 private:
  struct Level {
    float alpha, sigma, lambda;
  };
  static Level level(float sigma) {
    const float alpha = 1.0f / std::pow(sigma * sigma + 1.0f, 0.5f);
    const float s = sigma * alpha;
    return {alpha, s, std::log(alpha) - std::log(s)};
  }
  std::vector<float> sigmas_;
  at::Tensor previous_x0_;
  int64_t next_index_ = -1;
};

// diffusers' PNDMScheduler with skip_prk_steps: pseudo linear multistep (PLMS) steps only. The schedule
// repeats its second timestep: the first two steps form one Heun-like step (the second re-evaluates the
// model at the first step's result and averages both outputs, restarting from the first step's sample);
// later steps combine the last 2, 3, then 4 model outputs (Adams-Bashforth). Each step moves from the
// current timestep to the one num_train_timesteps / n below it with diffusers' transfer formula.
class Pndm final : public TimestepScheduler {
 public:
  explicit Pndm(const SchedulerConfig& c) : TimestepScheduler(c) {}
  void set_timesteps(int64_t n) override {
    set_integer_timesteps(n);  // descending
    if (n >= 2) timesteps_.insert(timesteps_.begin() + 1, timesteps_[1]);
    outputs_.clear();
    first_sample_ = at::Tensor();
    taken_ = 0;
    next_index_ = -1;
  }
  at::Tensor step(const at::Tensor& eps, int64_t i, const at::Tensor& sample) override {
    TORCH_CHECK(next_index_ < 0 || i == next_index_, "PNDM steps must run in order: expected step ", next_index_,
                ", got ", i);
    const at::Tensor e = eps.to(at::kFloat);
    at::Tensor x = sample.to(at::kFloat);
    auto t = static_cast<int64_t>(timesteps_.at(i));
    int64_t prev = t - stride_;
    if (taken_ == 1) {  // the repeated timestep: the step from t + stride to t again
      prev = t;
      t += stride_;
    } else {
      if (outputs_.size() == 4) outputs_.erase(outputs_.begin());
      outputs_.push_back(e);
    }
    at::Tensor direction;
    const size_t n = outputs_.size();
    if (n == 1 && taken_ == 0) {
      direction = e;
      first_sample_ = x;
    } else if (n == 1 && taken_ == 1) {
      direction = (e + outputs_[0]) / 2;
      x = first_sample_;
      first_sample_ = at::Tensor();
    } else if (n == 2) {
      direction = (3 * outputs_[1] - outputs_[0]) / 2;
    } else if (n == 3) {
      direction = (23 * outputs_[2] - 16 * outputs_[1] + 5 * outputs_[0]) / 12;
    } else {
      direction = (1.0 / 24) * (55 * outputs_[3] - 59 * outputs_[2] + 37 * outputs_[1] - 9 * outputs_[0]);
    }
    ++taken_;
    next_index_ = i + 1;
    return previous_sample(x, t, prev, direction).to(eps.scalar_type());
  }

 private:
  // diffusers' _get_prev_sample (formula (9) of the PNDM paper), in float32 like its 0-d tensors.
  at::Tensor previous_sample(const at::Tensor& x, int64_t t, int64_t prev, const at::Tensor& direction) const {
    const float abar = abar_at(alphas_cumprod_, t);
    const float abar_prev = abar_target(prev);
    const float sample_coeff = std::pow(abar_prev / abar, 0.5f);
    const float denominator =
        abar * std::pow(1.0f - abar_prev, 0.5f) + std::pow(abar * (1.0f - abar) * abar_prev, 0.5f);
    return sample_coeff * x - (abar_prev - abar) * direction / denominator;
  }
  std::vector<at::Tensor> outputs_;  // the last (up to) 4 model outputs
  at::Tensor first_sample_;          // the sample before the first step, for the repeated timestep
  int64_t taken_ = 0;                // steps since set_timesteps
  int64_t next_index_ = -1;
};

}  // namespace

absl::StatusOr<SchedulerConfig> SchedulerConfig::from_json(const nlohmann::json& j, const std::string& kind_override) {
  SchedulerConfig c;
  GAPS_ASSIGN_OR_RETURN(std::string class_name, config_value<std::string>(j, "_class_name", "EulerDiscreteScheduler"));
  if (!kind_override.empty()) {
    c.kind = kind_override;
  } else if (class_name == "EulerDiscreteScheduler") {
    c.kind = "euler";
  } else if (class_name == "DDIMScheduler") {
    c.kind = "ddim";
  } else if (class_name == "DPMSolverMultistepScheduler") {
    c.kind = "dpmpp2m";
  } else if (class_name == "PNDMScheduler") {
    c.kind = "pndm";
  } else {
    return absl::UnimplementedError(
        absl::StrCat("scheduler ", class_name, " is not supported (euler, ddim, dpmpp2m, pndm are)"));
  }
  if (c.kind != "euler" && c.kind != "ddim" && c.kind != "dpmpp2m" && c.kind != "pndm") {
    return absl::InvalidArgumentError(absl::StrCat("unknown scheduler '", c.kind, "' (euler, ddim, dpmpp2m, pndm)"));
  }
  const bool pndm = c.kind == "pndm";
  GAPS_ASSIGN_OR_RETURN(c.num_train_timesteps, config_value<int64_t>(j, "num_train_timesteps", 1000));
  GAPS_ASSIGN_OR_RETURN(c.steps_offset, config_value<int64_t>(j, "steps_offset", 0));
  GAPS_ASSIGN_OR_RETURN(c.beta_start, config_value<double>(j, "beta_start", 0.0001));
  GAPS_ASSIGN_OR_RETURN(c.beta_end, config_value<double>(j, "beta_end", 0.02));
  GAPS_ASSIGN_OR_RETURN(c.beta_schedule, config_value<std::string>(j, "beta_schedule", "linear"));
  GAPS_ASSIGN_OR_RETURN(
      c.timestep_spacing,
      config_value<std::string>(j, "timestep_spacing", pndm || c.kind == "ddim" ? "leading" : "linspace"));
  // Keys a config lacks take the chosen scheduler's diffusers defaults (as from_config does).
  GAPS_ASSIGN_OR_RETURN(c.clip_sample, config_value<bool>(j, "clip_sample", c.kind == "ddim"));
  GAPS_ASSIGN_OR_RETURN(c.set_alpha_to_one, config_value<bool>(j, "set_alpha_to_one", !pndm));
  if (pndm) {
    // PNDMScheduler's own default is false (Runge-Kutta warm-up steps); Stable Diffusion's folders set true.
    GAPS_ASSIGN_OR_RETURN(const bool skip_prk, config_value<bool>(j, "skip_prk_steps", false));
    if (!skip_prk) {
      return absl::UnimplementedError(
          "PNDM is implemented with skip_prk_steps true only (PLMS steps, as Stable Diffusion's scheduler configs "
          "set)");
    }
  }
  if (c.beta_schedule != "scaled_linear" && c.beta_schedule != "linear") {
    return absl::UnimplementedError(absl::StrCat("beta_schedule ", c.beta_schedule, " is not supported"));
  }
  if (c.timestep_spacing != "leading" && c.timestep_spacing != "trailing" && c.timestep_spacing != "linspace") {
    return absl::InvalidArgumentError(
        absl::StrCat("timestep_spacing ", c.timestep_spacing, " is not one of leading, trailing, linspace"));
  }
  GAPS_ASSIGN_OR_RETURN(auto prediction, config_value<std::string>(j, "prediction_type", "epsilon"));
  if (prediction != "epsilon") return absl::UnimplementedError("prediction_type " + prediction + " is not supported");
  for (const char* key : {"use_karras_sigmas", "use_exponential_sigmas", "use_beta_sigmas", "use_lu_lambdas",
                          "thresholding", "rescale_betas_zero_snr", "euler_at_final"}) {
    GAPS_ASSIGN_OR_RETURN(bool on, config_value<bool>(j, key, false));
    if (on) return absl::UnimplementedError(absl::StrCat("scheduler option ", key, " is not supported"));
  }
  GAPS_ASSIGN_OR_RETURN(auto interpolation, config_value<std::string>(j, "interpolation_type", "linear"));
  GAPS_ASSIGN_OR_RETURN(auto final_sigmas, config_value<std::string>(j, "final_sigmas_type", "zero"));
  GAPS_ASSIGN_OR_RETURN(auto algorithm, config_value<std::string>(j, "algorithm_type", "dpmsolver++"));
  GAPS_ASSIGN_OR_RETURN(auto solver_order, config_value<int64_t>(j, "solver_order", 2));
  GAPS_ASSIGN_OR_RETURN(auto solver_type, config_value<std::string>(j, "solver_type", "midpoint"));
  if (interpolation != "linear" || final_sigmas != "zero") {
    return absl::UnimplementedError("only linear sigma interpolation and final_sigmas_type 'zero' are supported");
  }
  if (c.kind == "dpmpp2m" && class_name == "DPMSolverMultistepScheduler" &&
      (algorithm != "dpmsolver++" || solver_order != 2 || solver_type != "midpoint")) {
    return absl::UnimplementedError("only DPM-Solver++ of order 2 with the midpoint solver is supported");
  }
  return c;
}

Scheduler::Scheduler(const SchedulerConfig& c) : config_(c) {
  const int64_t n = c.num_train_timesteps;
  const at::Tensor betas = c.beta_schedule == "scaled_linear"
                               ? at::linspace(std::sqrt(c.beta_start), std::sqrt(c.beta_end), n, at::kFloat).pow(2)
                               : at::linspace(c.beta_start, c.beta_end, n, at::kFloat);
  alphas_cumprod_ = at::cumprod(1.0 - betas, 0).contiguous();
}

std::vector<double> Scheduler::spaced_timesteps(int64_t n, bool one_extra_for_dpm) const {
  const int64_t train = config_.num_train_timesteps;
  std::vector<double> t;
  if (config_.timestep_spacing == "linspace") {
    // DPM spaces n + 1 points and drops the last (t = 0); the others space n points.
    const int64_t points = one_extra_for_dpm ? n + 1 : n;
    for (int64_t i = points - 1; i >= (one_extra_for_dpm ? 1 : 0); --i) {
      const double v = points == 1 ? 0.0 : static_cast<double>(train - 1) * i / (points - 1);
      t.push_back(one_extra_for_dpm || config_.kind != "euler" ? std::nearbyint(v) : v);
    }
  } else if (config_.timestep_spacing == "leading") {
    const int64_t points = one_extra_for_dpm ? n + 1 : n;
    const int64_t ratio = train / points;
    for (int64_t i = points - 1; i >= (one_extra_for_dpm ? 1 : 0); --i)
      t.push_back(static_cast<double>(i * ratio + config_.steps_offset));
  } else {
    const double ratio = static_cast<double>(train) / n;
    for (int64_t i = 0; i < n; ++i) t.push_back(std::nearbyint(train - i * ratio) - 1);
  }
  return t;
}

absl::StatusOr<std::unique_ptr<Scheduler>> make_scheduler(const SchedulerConfig& config) {
  if (config.kind == "euler") return std::unique_ptr<Scheduler>(new EulerDiscrete(config));
  if (config.kind == "ddim") return std::unique_ptr<Scheduler>(new Ddim(config));
  if (config.kind == "dpmpp2m") return std::unique_ptr<Scheduler>(new DpmSolverPP2M(config));
  if (config.kind == "pndm") return std::unique_ptr<Scheduler>(new Pndm(config));
  return absl::InvalidArgumentError(absl::StrCat("unknown scheduler '", config.kind, "'"));
}

at::Tensor classifier_free_guidance(const at::Tensor& stacked, double guidance_scale) {
  const auto parts = stacked.chunk(2, 0);
  return parts[0] + guidance_scale * (parts[1] - parts[0]);
}

}  // namespace gaps::sdxl

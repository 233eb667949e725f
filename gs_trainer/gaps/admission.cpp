#include "gs_trainer/gaps/admission.h"

#include <ATen/ATen.h>

#include <algorithm>
#include <cmath>

#include <absl/strings/str_format.h>

#include "gs_trainer/raster/losses.h"

namespace gaps {

namespace {

void check_image(const at::Tensor& image, const char* what) {
  TORCH_CHECK(image.dim() == 3 && image.size(2) == 3, what, ": expected an HxWx3 image, got shape ", image.sizes());
}

std::string coverage_reason(double mean_alpha, const GapsConfig& c) {
  const bool ok = mean_alpha >= c.admit_min_alpha;
  return absl::StrFormat("mean alpha %.4f %s %.4g", mean_alpha, ok ? ">=" : "<", c.admit_min_alpha);
}

std::string residual_reason(double mean_residual, const GapsConfig& c) {
  const bool ok = mean_residual < c.admit_max_residual;
  return absl::StrFormat("mean residual %.4f %s %.4g", mean_residual, ok ? "<" : ">=", c.admit_max_residual);
}

}  // namespace

at::Tensor uncertainty_map(const at::Tensor& hallucinated, const at::Tensor& rendered) {
  check_image(hallucinated, "hallucinated");
  check_image(rendered, "rendered");
  TORCH_CHECK(hallucinated.sizes() == rendered.sizes(), "image shapes differ: ", hallucinated.sizes(), " vs ",
              rendered.sizes());
  return (hallucinated - rendered).abs().mean(2);
}

double uncertainty_variance(const at::Tensor& uncertainty) {
  return uncertainty.to(at::kDouble).square().mean().item<double>();
}

AdmissionDecision decide_admission(double mean_alpha, double mean_residual, const GapsConfig& c) {
  AdmissionDecision d;
  d.mean_alpha = mean_alpha;
  d.mean_residual = mean_residual;
  const bool covered = mean_alpha >= c.admit_min_alpha;
  const bool consistent = mean_residual < c.admit_max_residual;
  d.admitted = covered && consistent;
  if (d.admitted) {
    d.reason = "admitted: " + coverage_reason(mean_alpha, c) + ", " + residual_reason(mean_residual, c);
  } else {
    d.reason = "rejected:";
    if (!covered) d.reason += " coverage (" + coverage_reason(mean_alpha, c) + ")";
    if (!consistent) d.reason += " consistency (" + residual_reason(mean_residual, c) + ")";
  }
  return d;
}

at::Tensor generator_proposal(const at::Tensor& hallucinated, const at::Tensor& rendered, double strength) {
  check_image(hallucinated, "hallucinated");
  check_image(rendered, "rendered");
  return (rendered + (hallucinated - rendered) / std::max(strength, 0.05)).clamp(0, 1);
}

namespace {

// Mean of an H×W map over the pixels of `mask` (H×W, 0/1), or over all pixels when the mask is empty.
double masked_mean(const at::Tensor& map, const at::Tensor& mask) {
  const double count = mask.sum().item<double>();
  if (count < 1) return map.to(at::kDouble).mean().item<double>();
  return (map.to(at::kDouble) * mask).sum().item<double>() / count;
}

std::string structure_reason(double structure, const GapsConfig& c) {
  const bool ok = structure >= c.admit_min_structure;
  return absl::StrFormat("SSIM to the render %.4f %s %.4g", structure, ok ? ">=" : "<", c.admit_min_structure);
}

}  // namespace

AdmissionDecision admit_pseudo_view(const at::Tensor& hallucinated, const at::Tensor& rendered, const at::Tensor& alpha,
                                    const GapsConfig& c, double strength) {
  const at::Tensor judged = c.admit_on_proposal ? generator_proposal(hallucinated, rendered, strength) : hallucinated;
  const at::Tensor u = uncertainty_map(judged, rendered);
  const at::Tensor mask = c.admit_on_proposal ? (alpha >= c.coverage_alpha_threshold).to(at::kDouble)
                                              : at::ones_like(alpha, alpha.options().dtype(at::kDouble));
  const double mean_alpha = alpha.to(at::kDouble).mean().item<double>();
  AdmissionDecision d = decide_admission(mean_alpha, masked_mean(u, mask), c);
  d.uncertainty = u;
  if (c.admit_min_structure <= 0) return d;
  const at::Tensor ssim = ssim_map(judged.to(at::kFloat).contiguous(), rendered.to(at::kFloat).contiguous()).mean(2);
  d.structure = masked_mean(ssim, mask);
  const bool structured = *d.structure >= c.admit_min_structure;
  const std::string reason = structure_reason(*d.structure, c);
  if (structured) {
    d.reason += d.admitted ? ", " + reason : "";
  } else {
    d.reason = (d.admitted ? std::string("rejected:") : d.reason) + " structure (" + reason + ")";
    d.admitted = false;
  }
  return d;
}

at::Tensor confidence_weight(const at::Tensor& alpha, const at::Tensor& uncertainty, const GapsConfig& c) {
  TORCH_CHECK(alpha.sizes() == uncertainty.sizes(), "alpha ", alpha.sizes(), " and uncertainty ", uncertainty.sizes(),
              " must have one shape");
  const at::Tensor max_u = uncertainty.max();
  return alpha * (1.0 - c.uncertainty_lambda * uncertainty / (max_u + c.uncertainty_eps));
}

double extrapolation_decay(double d_extrap, const GapsConfig& c) { return std::exp(-c.extrap_kappa * d_extrap); }

at::Tensor pseudo_pixel_weight(const at::Tensor& alpha, const at::Tensor& uncertainty, double d_extrap,
                               const GapsConfig& c) {
  return (c.pseudo_loss_weight * extrapolation_decay(d_extrap, c)) * confidence_weight(alpha, uncertainty, c);
}

double drop_threshold(const GapsConfig& c, int64_t gaussian_budget) {
  if (gaussian_budget <= 0 || c.drop_budget_fraction <= 0) return c.drop_n_ref;
  return std::min(c.drop_n_ref, c.drop_budget_fraction * static_cast<double>(gaussian_budget));
}

double drop_ratio(int iteration, int total_iterations, int64_t num_gaussians, const GapsConfig& c,
                  int64_t gaussian_budget) {
  const double progress =
      total_iterations > 0 ? std::clamp(static_cast<double>(iteration) / total_iterations, 0.0, 1.0) : 1.0;
  const double density = std::min(static_cast<double>(num_gaussians) / drop_threshold(c, gaussian_budget), 1.0);
  return c.drop_max * progress * density;
}

at::Tensor drop_gaussian_scale(int64_t num_gaussians, double ratio, std::optional<at::Generator> generator,
                               const at::TensorOptions& options) {
  TORCH_CHECK(ratio >= 0.0 && ratio < 1.0, "drop ratio must be in [0, 1), got ", ratio);
  at::TensorOptions opts = options.has_dtype() ? options : options.dtype(at::kFloat);
  at::Tensor keep = at::empty({num_gaussians}, opts).bernoulli_(1.0 - ratio, generator);
  return keep.mul_(1.0 / (1.0 - ratio));  // the (1 - r)^-1 compensation keeps E[α'] = α
}

double adaptive_strength(double coverage, const GapsConfig& c) {
  return c.strength_max - std::clamp(coverage, 0.0, 1.0) * (c.strength_max - c.strength_min);
}

double adaptive_control_scale(double coverage, const GapsConfig& c) {
  return c.cn_scale * std::min(1.0, std::max(0.0, coverage) / c.cn_coverage);
}

}  // namespace gaps

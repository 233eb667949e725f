#pragma once
// The paper's two-stage generation for incomplete views (eq. two_stage): where the rendered depth of a
// pseudo-view falls below tau_d (no Gaussian support), the uncovered mask is dilated by a 15 x 15 square
// kernel and, when more than 2% of the view is uncovered, an inpainting model (SD2 inpainting,
// inpaint_pipeline.h) regenerates the masked pixels of the stage-1 image I_s1; the result is
//   I_pseudo = M * I_s2 + (1 - M) * I_s1.
#include <functional>
#include <limits>
#include <string>
#include <vector>

#include <ATen/Tensor.h>
#include "absl/status/statusor.h"
#include "diffusion_worker/sdxl/inpaint_pipeline.h"

namespace gaps::sdxl {

struct TwoStageOptions {
  double depth_threshold = std::numeric_limits<double>::quiet_NaN();  // tau_d (required, finite)
  double min_uncovered_fraction = 0.02;  // inpaint only views with a larger uncovered fraction
  int64_t dilation_kernel = 15;          // side of the square dilation kernel (odd)
  InpaintParams inpaint;                 // the second stage's schedule, strength and guidance
};

// 1 where depth < depth_threshold, else 0: B x 1 x H x W float32 from depth B x 1 x H x W or B x H x W.
at::Tensor uncovered_mask(const at::Tensor& depth, double depth_threshold);
// The fraction of each view's pixels the mask covers (B, float64).
std::vector<double> uncovered_fractions(const at::Tensor& mask);
// Binary dilation with a kernel x kernel square (odd kernel): a pixel is 1 when any pixel within
// kernel / 2 of it (Chebyshev distance) is 1; the border is not replicated.
at::Tensor dilate_mask(const at::Tensor& mask, int64_t kernel);
// eq. two_stage: mask * stage2 + (1 - mask) * stage1 (mask broadcast over the channels).
at::Tensor composite_two_stage(const at::Tensor& stage1, const at::Tensor& stage2, const at::Tensor& mask);

struct TwoStageResult {
  at::Tensor images;              // B x 3 x H x W in [0, 1]
  std::vector<double> uncovered;  // per view, before dilation
  std::vector<bool> inpainted;    // per view: uncovered > min_uncovered_fraction
};

// Gets the inpainting pipeline; called only when some view needs the second stage (so it may load lazily).
using InpaintPipelineSource = std::function<absl::StatusOr<InpaintPipeline*>()>;

// stage1: B x 3 x H x W in [0, 1]; depth: the renders' depth (B x 1 x H x W or B x H x W, 0 where nothing
// was rendered); prompts: one for all or one per view; seeds: one per view. Views at or below the
// uncovered fraction keep their stage-1 image; the others are inpainted together (each with its seed)
// under their dilated masks (padded, replicated, to the inpainting model's latent factor and cropped back)
// and composited.
absl::StatusOr<TwoStageResult> two_stage_generate(const at::Tensor& stage1, const at::Tensor& depth,
                                                  const std::vector<std::string>& prompts,
                                                  const std::vector<uint64_t>& seeds, const TwoStageOptions& options,
                                                  const InpaintPipelineSource& pipeline);

}  // namespace gaps::sdxl

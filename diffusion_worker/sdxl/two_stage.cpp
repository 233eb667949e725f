#include "diffusion_worker/sdxl/two_stage.h"

#include <cmath>

#include <ATen/ATen.h>
#include "absl/strings/str_cat.h"
#include "common/status_macros.h"

namespace gaps::sdxl {

at::Tensor uncovered_mask(const at::Tensor& depth, double depth_threshold) {
  const at::Tensor d = depth.dim() == 3 ? depth.unsqueeze(1) : depth;
  return (d < depth_threshold).to(at::kFloat);
}

std::vector<double> uncovered_fractions(const at::Tensor& mask) {
  const at::Tensor f = mask.to(at::kCPU, at::kDouble).flatten(1).mean(1).contiguous();
  return std::vector<double>(f.data_ptr<double>(), f.data_ptr<double>() + f.numel());
}

at::Tensor dilate_mask(const at::Tensor& mask, int64_t kernel) {
  TORCH_CHECK(kernel >= 1 && kernel % 2 == 1, "dilate_mask: the kernel must be a positive odd size, got ", kernel);
  // Max pooling with stride 1 is dilation with a square; its padding never wins a max over a 0/1 mask.
  return at::max_pool2d(mask.to(at::kFloat), {kernel, kernel}, {1, 1}, {kernel / 2, kernel / 2});
}

at::Tensor composite_two_stage(const at::Tensor& stage1, const at::Tensor& stage2, const at::Tensor& mask) {
  return mask * stage2 + (1 - mask) * stage1;
}

namespace {

absl::Status check_two_stage_inputs(const at::Tensor& stage1, const at::Tensor& depth,
                                    const std::vector<std::string>& prompts, const std::vector<uint64_t>& seeds,
                                    const TwoStageOptions& o) {
  if (!stage1.defined() || stage1.dim() != 4 || stage1.size(1) != 3) {
    return absl::InvalidArgumentError("two-stage generation: the stage-1 images must be B x 3 x H x W");
  }
  const int64_t b = stage1.size(0), h = stage1.size(2), w = stage1.size(3);
  const bool depth_ok =
      depth.defined() &&
      ((depth.dim() == 3 && depth.size(0) == b && depth.size(1) == h && depth.size(2) == w) ||
       (depth.dim() == 4 && depth.size(0) == b && depth.size(1) == 1 && depth.size(2) == h && depth.size(3) == w));
  if (!depth_ok) {
    return absl::InvalidArgumentError(absl::StrCat("two-stage generation: the depth must be ", b, " x [1 x] ", h, " x ",
                                                   w, " like the stage-1 images"));
  }
  if (!std::isfinite(o.depth_threshold)) {
    return absl::InvalidArgumentError("two-stage generation: depth_threshold (tau_d) must be set to a finite value");
  }
  if (!(o.min_uncovered_fraction >= 0 && o.min_uncovered_fraction < 1)) {
    return absl::InvalidArgumentError("two-stage generation: min_uncovered_fraction must be in [0, 1)");
  }
  if (o.dilation_kernel < 1 || o.dilation_kernel % 2 == 0) {
    return absl::InvalidArgumentError("two-stage generation: dilation_kernel must be a positive odd size");
  }
  if (prompts.size() != 1 && static_cast<int64_t>(prompts.size()) != b) {
    return absl::InvalidArgumentError("two-stage generation: give one prompt, or one per view");
  }
  if (static_cast<int64_t>(seeds.size()) != b)
    return absl::InvalidArgumentError("two-stage generation: give one seed per view");
  return absl::OkStatus();
}

}  // namespace

absl::StatusOr<TwoStageResult> two_stage_generate(const at::Tensor& stage1, const at::Tensor& depth,
                                                  const std::vector<std::string>& prompts,
                                                  const std::vector<uint64_t>& seeds, const TwoStageOptions& options,
                                                  const InpaintPipelineSource& pipeline) {
  GAPS_RETURN_IF_ERROR(check_two_stage_inputs(stage1, depth, prompts, seeds, options));
  TwoStageResult result;
  const at::Tensor uncovered = uncovered_mask(depth.to(at::kCPU), options.depth_threshold);
  result.uncovered = uncovered_fractions(uncovered);
  result.images = stage1.to(at::kCPU, at::kFloat).clone();
  std::vector<int64_t> views;
  std::vector<std::string> view_prompts;
  std::vector<uint64_t> view_seeds;
  for (int64_t i = 0; i < stage1.size(0); ++i) {
    const bool inpaint = result.uncovered[i] > options.min_uncovered_fraction;
    result.inpainted.push_back(inpaint);
    if (!inpaint) continue;
    views.push_back(i);
    view_prompts.push_back(prompts.size() == 1 ? prompts[0] : prompts[i]);
    view_seeds.push_back(seeds[i]);
  }
  if (views.empty()) return result;
  GAPS_ASSIGN_OR_RETURN(InpaintPipeline * inpainter, pipeline());
  const at::Tensor index = at::tensor(views, at::kLong);
  const at::Tensor masks = dilate_mask(uncovered.index_select(0, index), options.dilation_kernel);
  const at::Tensor selected = result.images.index_select(0, index);
  // The inpainting model needs sizes divisible by its latent factor: pad at the bottom/right edge
  // (replicated) and crop its output back; the fraction and the composite use the view's own pixels.
  const int64_t f = inpainter->latent_factor(), h = selected.size(2), w = selected.size(3);
  const std::vector<int64_t> pad{0, (w + f - 1) / f * f - w, 0, (h + f - 1) / f * f - h};
  GAPS_ASSIGN_OR_RETURN(at::Tensor stage2,
                        inpainter->inpaint(at::replication_pad2d(selected, pad), at::replication_pad2d(masks, pad),
                                           view_prompts, options.inpaint, view_seeds));
  stage2 = stage2.slice(2, 0, h).slice(3, 0, w);
  result.images.index_copy_(0, index, composite_two_stage(selected, stage2, masks));
  return result;
}

}  // namespace gaps::sdxl

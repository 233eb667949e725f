#pragma once
// The ControlNet conditioning image of a pseudo view from the Gaussian field's render at its pose (paper,
// "Depth-conditioned generation via ControlNet"): a reliability mask zeroes pixels with too little alpha
// coverage (< τ_α) or a high local depth variance (depth edges, floaters), and the reliable pixels carry
// inverse depth normalised to [0, 1] by its range over them (near = bright, as SDXL depth ControlNets
// are trained on), repeated over 3 channels. The conditioning scale s_cn(v) of eq. adaptive_cn comes with
// the request (gs_trainer/gaps/admission.h, adaptive_control_scale).
#include <cstdint>

#include <ATen/Tensor.h>
#include "absl/status/statusor.h"

namespace gaps {

struct DepthControlOptions {
  // τ_α: a pixel with rendered alpha below this is unreliable (gaps_config's coverage threshold, 0.5).
  double min_alpha = 0.5;
  // Side (odd) of the square window of the local depth statistics.
  int64_t variance_window = 3;
  // A pixel whose window has Var(d) / mean(d)² above this is unreliable (d: expected distance over the
  // window's covered pixels). Scale-free; 0.01 = a standard deviation of 10% of the local mean depth,
  // which flags depth edges and floaters while slanted smooth surfaces stay far below it.
  double max_relative_variance = 0.01;
};

struct DepthControl {
  at::Tensor image;     // 3 x H x W float32 in [0, 1]: normalised inverse depth on reliable pixels, 0 elsewhere
  at::Tensor reliable;  // H x W bool
};

// depth: H x W rendered depth (eq. depth_render, alpha-weighted, so the expected distance is depth /
// alpha); alpha: H x W. Per pixel, with d = depth / alpha:
//   covered  = alpha >= min_alpha and d > 0 (finite)
//   m, m2    = mean of d and of d² over the covered pixels of the window around it
//   reliable = covered and (m2 - m²) / m² <= max_relative_variance
//   value    = (1/d - min) / (max - min), min and max of 1/d over the reliable pixels (1 when they are
//              equal), 0 on unreliable pixels.
// Bad shapes or options are an error.
absl::StatusOr<DepthControl> depth_control_image(const at::Tensor& depth, const at::Tensor& alpha,
                                                 const DepthControlOptions& options = {});

// A monocular disparity map (Depth-Anything's output: larger is nearer, arbitrary scale and shift), H x W,
// as a ControlNet image: (disparity - min) / (max - min) on 3 channels, as depth ControlNets were trained
// on; a constant map gives ones. Every pixel is reliable.
absl::StatusOr<DepthControl> disparity_control_image(const at::Tensor& disparity);

}  // namespace gaps

#pragma once
// The differentiable rasterizer: three autograd operations, the same on every device, and the compositing over a
// background.
//   shade_gaussians:     3D means, SH coefficients, camera centre -> colour and distance per Gaussian
//   project_gaussians:   3D means, quaternions, scales  -> 2D means, conics (+ depths, radii)
//   rasterize_gaussians: 2D Gaussians, opacities, per-Gaussian features -> feature image, alpha
// Features are any number of channels composited with the same weights (colour, depth, ...). The CPU
// implementation is the reference; the CUDA one must match it (see tests/rasterizer_test.cpp).
#include <array>
#include <vector>

#include <ATen/Tensor.h>

#include "gs_trainer/raster/raster_math.h"

namespace gaps {

// N x 4: colour max(SH(view direction) + 0.5, 0) with the first (degree + 1)^2 coefficients (sh_dc N x 1 x 3,
// sh_rest N x R x 3), and the distance from `centre` (what the paper's depth composites). The readable
// reference is sh_to_color (spherical_harmonics.h) plus a norm.
at::Tensor shade_gaussians(const at::Tensor& means, const at::Tensor& sh_dc, const at::Tensor& sh_rest, int degree,
                           const std::array<double, 3>& centre);

struct ProjectedGaussians {
  at::Tensor means2d;  // N x 2, differentiable (its gradient drives densification)
  at::Tensor conics;   // N x 3, differentiable
  at::Tensor depths;   // N, camera z (not differentiable; the sort key)
  at::Tensor radii;    // N int32, 0 where culled
};

ProjectedGaussians project_gaussians(const at::Tensor& means, const at::Tensor& quats, const at::Tensor& scales,
                                     const at::Tensor& viewmat, const raster::Intrinsics& intrinsics);

struct RasterizedImage {
  at::Tensor features;  // H x W x C
  at::Tensor alpha;     // H x W, 1 - final transmittance
};

// `means2d_abs_sink`, when defined (N x 2), receives in the backward pass the per-Gaussian sum of absolute
// per-pixel 2D-mean gradients (the absolute-gradient densification criterion).
RasterizedImage rasterize_gaussians(const at::Tensor& means2d, const at::Tensor& conics, const at::Tensor& opacities,
                                    const at::Tensor& features, const at::Tensor& depths, const at::Tensor& radii,
                                    int width, int height, const at::Tensor& means2d_abs_sink = {});

// rgb = the first three feature channels + (1 - alpha) * background: the image over a background colour (3 values on
// the features' device), differentiable in features and alpha.
at::Tensor composite_over_background(const at::Tensor& features, const at::Tensor& alpha, const at::Tensor& background);

// Forward-only renders of the same Gaussians from V cameras of one image size (no autograd graph): viewmats
// V x 4 x 4, centres the V camera centres, intrinsics one per view (all of one width and height). Stacked: features V x
// H x W x 4 (shade_gaussians' colour and distance composited), alpha V x H x W; view v equals shade_gaussians,
// project_gaussians and rasterize_gaussians of that view alone, bit for bit. Each stage runs through the backend for
// all views at once: on CUDA one launch per kernel (the shading reads every Gaussian's coefficients once for all views)
// and one host synchronisation, so scoring hundreds of small views keeps the device full and never waits on the host
// between views.
RasterizedImage render_views_forward(const at::Tensor& means, const at::Tensor& quats, const at::Tensor& scales,
                                     const at::Tensor& opacities, const at::Tensor& sh_dc, const at::Tensor& sh_rest,
                                     int degree, const at::Tensor& viewmats,
                                     const std::vector<std::array<double, 3>>& centres,
                                     const std::vector<raster::Intrinsics>& intrinsics);

}  // namespace gaps

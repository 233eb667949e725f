#pragma once
// The rasterizer's stages as plain tensor functions, one implementation per device (cpu/, cuda/).
// rasterizer.cpp wraps them as autograd functions through backend.h's table; besides, only tests and
// benchmarks call them, by name.
#include <tuple>
#include <vector>

#include <ATen/Tensor.h>
#include "gs_trainer/raster/raster_math.h"

namespace gaps::backend {

struct Projection {
  at::Tensor means2d;  // N x 2
  at::Tensor conics;   // N x 3  (a, b, c) of the inverse dilated 2D covariance
  at::Tensor depths;   // N      camera-space z
  at::Tensor radii;    // N      int32, 0 = culled
};

struct ProjectionGrads {
  at::Tensor means, quats, scales;
};

// Gaussians sorted front to back inside each 16x16 tile.
struct TileBins {
  at::Tensor gaussian_ids;  // M int32, tile-major then depth order
  at::Tensor tile_ranges;   // T x 2 int32, [begin, end) into gaussian_ids per tile (row-major tiles)
};

struct RasterOutput {
  at::Tensor features;   // H x W x C
  at::Tensor alpha;      // H x W
  at::Tensor final_T;    // H x W transmittance after the last contributor
  at::Tensor n_contrib;  // H x W int32, entries of the tile list walked up to the last contributor
};

// Uninitialised outputs of one forward pass (both backends write every pixel), in `options`' dtype and device.
RasterOutput empty_raster_output(int height, int width, int channels, const at::TensorOptions& options);

struct ShadeGrads {
  at::Tensor means, sh_dc, sh_rest;
};

// Camera centre of the view being shaded (world coordinates).
struct Centre {
  double x, y, z;
};

struct RasterGrads {
  at::Tensor means2d, conics, opacities, features;
  at::Tensor means2d_abs;  // N x 2: sum over pixels of |dL/dmean2d| contributions (absolute-gradient densification)
};

// viewmat: 4x4 world-to-camera; all float tensors of one dtype (float32 or float64) on the CPU.
Projection project_forward_cpu(const at::Tensor& means, const at::Tensor& quats, const at::Tensor& scales,
                               const at::Tensor& viewmat, const raster::Intrinsics& K);
ProjectionGrads project_backward_cpu(const at::Tensor& means, const at::Tensor& quats, const at::Tensor& scales,
                                     const at::Tensor& viewmat, const raster::Intrinsics& K, const at::Tensor& radii,
                                     const at::Tensor& g_means2d, const at::Tensor& g_conics);
// N x 4 per-Gaussian features (SH colour at the view direction, clamped at 0; distance to the centre).
// sh_dc: N x 1 x 3, sh_rest: N x R x 3 with R >= (degree + 1)^2 - 1.
at::Tensor shade_forward_cpu(const at::Tensor& means, const at::Tensor& sh_dc, const at::Tensor& sh_rest, int degree,
                             const Centre& centre);
ShadeGrads shade_backward_cpu(const at::Tensor& means, const at::Tensor& sh_dc, const at::Tensor& sh_rest, int degree,
                              const Centre& centre, const at::Tensor& g_features);
TileBins bin_tiles_cpu(const at::Tensor& means2d, const at::Tensor& conics, const at::Tensor& opacities,
                       const at::Tensor& radii, const at::Tensor& depths, int width, int height);
// ---- Several views of the same Gaussians at once, forward only (scoring candidate views). Outputs are stacked
// view-major: view v's rows are v·N .. v·N + N - 1, each view's values those of the one-view function.
// viewmats: V x 4 x 4 with V intrinsics of one image size.
Projection project_views_forward_cpu(const at::Tensor& means, const at::Tensor& quats, const at::Tensor& scales,
                                     const at::Tensor& viewmats, const std::vector<raster::Intrinsics>& K);
// Shading takes the projection's radii (V·N): rows of Gaussians culled in a view (radius 0) are zeros, as no tile
// reads them.
at::Tensor shade_views_forward_cpu(const at::Tensor& means, const at::Tensor& sh_dc, const at::Tensor& sh_rest,
                                   int degree, const std::vector<Centre>& centres, const at::Tensor& radii);
// Forward passes (binning and compositing) of `views` views of the same Gaussians at one image size, every input
// stacked view-major (views blocks of N rows), outputs stacked too: features (views·H) x W x C, alpha (views·H) x W,
// image v equal to bin_tiles + rasterize_forward of view v alone. The CUDA version bins and composites all views
// in one launch of each kernel and waits on the device once (the pair count), not once per view.
RasterOutput rasterize_views_forward_cpu(int views, const at::Tensor& means2d, const at::Tensor& conics,
                                         const at::Tensor& opacities, const at::Tensor& radii, const at::Tensor& depths,
                                         const at::Tensor& features, int width, int height);
RasterOutput rasterize_forward_cpu(const TileBins& bins, const at::Tensor& means2d, const at::Tensor& conics,
                                   const at::Tensor& opacities, const at::Tensor& features, int width, int height);
RasterGrads rasterize_backward_cpu(const TileBins& bins, const at::Tensor& means2d, const at::Tensor& conics,
                                   const at::Tensor& opacities, const at::Tensor& features, const RasterOutput& forward,
                                   const at::Tensor& g_features, const at::Tensor& g_alpha);

// rgb = the first three feature channels + (1 - alpha) * background (3 values): H x W x 3. Its backward gives
// dL/dfeatures (H x W x channels, zero past the third) and dL/dalpha (H x W). The CPU's are the ATen operations
// autograd differentiated when the compositing was written in them (CPU renders and gradients keep their bits).
struct BackgroundGrads {
  at::Tensor features, alpha;
};
at::Tensor over_background_forward_cpu(const at::Tensor& features, const at::Tensor& alpha,
                                       const at::Tensor& background);
BackgroundGrads over_background_backward_cpu(const at::Tensor& g_rgb, const at::Tensor& background, int64_t channels);

#if defined(GAPS_CUDA_KERNELS)
at::Tensor over_background_forward_cuda(const at::Tensor& features, const at::Tensor& alpha,
                                        const at::Tensor& background);
BackgroundGrads over_background_backward_cuda(const at::Tensor& g_rgb, const at::Tensor& background, int64_t channels);
Projection project_forward_cuda(const at::Tensor& means, const at::Tensor& quats, const at::Tensor& scales,
                                const at::Tensor& viewmat, const raster::Intrinsics& K);
ProjectionGrads project_backward_cuda(const at::Tensor& means, const at::Tensor& quats, const at::Tensor& scales,
                                      const at::Tensor& viewmat, const raster::Intrinsics& K, const at::Tensor& radii,
                                      const at::Tensor& g_means2d, const at::Tensor& g_conics);
at::Tensor shade_forward_cuda(const at::Tensor& means, const at::Tensor& sh_dc, const at::Tensor& sh_rest, int degree,
                              const Centre& centre);
ShadeGrads shade_backward_cuda(const at::Tensor& means, const at::Tensor& sh_dc, const at::Tensor& sh_rest, int degree,
                               const Centre& centre, const at::Tensor& g_features);
TileBins bin_tiles_cuda(const at::Tensor& means2d, const at::Tensor& conics, const at::Tensor& opacities,
                        const at::Tensor& radii, const at::Tensor& depths, int width, int height);
// One launch for all views; the shading reads each Gaussian's coefficients once for all of them.
Projection project_views_forward_cuda(const at::Tensor& means, const at::Tensor& quats, const at::Tensor& scales,
                                      const at::Tensor& viewmats, const std::vector<raster::Intrinsics>& K);
at::Tensor shade_views_forward_cuda(const at::Tensor& means, const at::Tensor& sh_dc, const at::Tensor& sh_rest,
                                    int degree, const std::vector<Centre>& centres, const at::Tensor& radii);
// Tile bins of `views` views stacked view-major (N = means2d.size(0) / views rows each) at one image size: view v's
// tile t is bin v·T + t, listing rows v·N + i in the order bin_tiles_cuda gives view v alone. bin_tiles_cuda is
// the case of one view.
TileBins bin_tiles_views_cuda(int views, const at::Tensor& means2d, const at::Tensor& conics,
                              const at::Tensor& opacities, const at::Tensor& radii, const at::Tensor& depths, int width,
                              int height);
RasterOutput rasterize_views_forward_cuda(int views, const at::Tensor& means2d, const at::Tensor& conics,
                                          const at::Tensor& opacities, const at::Tensor& radii,
                                          const at::Tensor& depths, const at::Tensor& features, int width, int height);
RasterOutput rasterize_forward_cuda(const TileBins& bins, const at::Tensor& means2d, const at::Tensor& conics,
                                    const at::Tensor& opacities, const at::Tensor& features, int width, int height);
// `absolute_grads` = false leaves RasterGrads::means2d_abs undefined and saves its sums.
RasterGrads rasterize_backward_cuda(const TileBins& bins, const at::Tensor& means2d, const at::Tensor& conics,
                                    const at::Tensor& opacities, const at::Tensor& features,
                                    const RasterOutput& forward, const at::Tensor& g_features,
                                    const at::Tensor& g_alpha, bool absolute_grads = true);
#endif

}  // namespace gaps::backend

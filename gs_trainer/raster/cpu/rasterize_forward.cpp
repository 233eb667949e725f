// Front-to-back compositing per 16x16 tile on the CPU: features (colour, depth, ...), alpha, and the
// per-pixel state the backward pass needs (final transmittance, how far the tile list was walked).
// Loops run Gaussian-major over a tile's pixels, a SIMD vector of pixels of one row at a time (pixels are
// independent given the Gaussian order), visiting only the rows a Gaussian can reach and stopping when
// every pixel of the tile is saturated. The kernel is rasterize_forward_kernels.h, compiled once per
// instruction set (simd.h).
// Everything the kernel headers use comes first: they are compiled under target pragmas.
#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <new>
#include <type_traits>
#include <utility>
#include <vector>

#if defined(__x86_64__)
#include <immintrin.h>
#endif

#include <ATen/ATen.h>
#include <ATen/Dispatch.h>
#include <ATen/Parallel.h>

#include "gs_trainer/raster/cpu/parallel.h"
#include "gs_trainer/raster/cpu/rasterize_tile.h"
#include "gs_trainer/raster/cpu/simd.h"
#include "gs_trainer/raster/rasterize_backend.h"

namespace gaps::backend {
namespace {

template <typename T>
struct ForwardArgs {
  const int32_t* ids;
  const int32_t* ranges;
  const tile::Splat<T>* splats;
  const T* feat;
  int width, height, tiles_x, channels;
  T *out_feat, *out_alpha, *out_final_T;
  int32_t* out_n_contrib;
};

}  // namespace
}  // namespace gaps::backend

#define GAPS_SIMD_KERNELS "gs_trainer/raster/cpu/rasterize_forward_kernels.h"
#include "gs_trainer/raster/cpu/simd_multiversion.h"
#undef GAPS_SIMD_KERNELS

namespace gaps::backend {

RasterOutput rasterize_forward_cpu(const TileBins& bins, const at::Tensor& means2d_in, const at::Tensor& conics_in,
                                   const at::Tensor& opacities_in, const at::Tensor& features_in, int width,
                                   int height) {
  const auto means2d = means2d_in.contiguous(), conics = conics_in.contiguous();
  const auto opacities = opacities_in.contiguous(), features = features_in.contiguous();
  const int channels = static_cast<int>(features.size(1));
  const auto opts = features.options();
  // Every pixel is written by its tile.
  RasterOutput out = empty_raster_output(height, width, channels, opts);
  AT_DISPATCH_FLOATING_TYPES(features.scalar_type(), "rasterize_forward_cpu", [&] {
    const auto splats = tile::make_splats(means2d.size(0), means2d.data_ptr<scalar_t>(), conics.data_ptr<scalar_t>(),
                                          opacities.data_ptr<scalar_t>());
    const ForwardArgs<scalar_t> in{bins.gaussian_ids.data_ptr<int32_t>(),
                                   bins.tile_ranges.data_ptr<int32_t>(),
                                   splats.data(),
                                   features.data_ptr<scalar_t>(),
                                   width,
                                   height,
                                   (width + raster::kTileSize - 1) / raster::kTileSize,
                                   channels,
                                   out.features.data_ptr<scalar_t>(),
                                   out.alpha.data_ptr<scalar_t>(),
                                   out.final_T.data_ptr<scalar_t>(),
                                   out.n_contrib.data_ptr<int32_t>()};
    const auto kernel =
        simd::pick_for_isa(&avx512::composite_tile_entry<scalar_t>, &avx2::composite_tile_entry<scalar_t>,
                           &baseline::composite_tile_entry<scalar_t>);
    parallel_for_each_dynamic(bins.tile_ranges.size(0), [&](int64_t t) { kernel(t, in); });
  });
  return out;
}

RasterOutput rasterize_views_forward_cpu(int views, const at::Tensor& means2d, const at::Tensor& conics,
                                         const at::Tensor& opacities, const at::Tensor& radii, const at::Tensor& depths,
                                         const at::Tensor& features, int width, int height) {
  TORCH_CHECK(views >= 1 && means2d.size(0) % views == 0, "rasterize_views_forward_cpu: ", means2d.size(0),
              " rows do not split into ", views, " views");
  const int64_t n = means2d.size(0) / views;
  std::vector<at::Tensor> feats, alphas, final_T, n_contrib;
  for (int v = 0; v < views; ++v) {
    const auto rows = [&](const at::Tensor& t) { return t.narrow(0, v * n, n); };
    const TileBins bins =
        bin_tiles_cpu(rows(means2d), rows(conics), rows(opacities), rows(radii), rows(depths), width, height);
    const RasterOutput out =
        rasterize_forward_cpu(bins, rows(means2d), rows(conics), rows(opacities), rows(features), width, height);
    feats.push_back(out.features);
    alphas.push_back(out.alpha);
    final_T.push_back(out.final_T);
    n_contrib.push_back(out.n_contrib);
  }
  return {at::cat(feats), at::cat(alphas), at::cat(final_T), at::cat(n_contrib)};
}

}  // namespace gaps::backend

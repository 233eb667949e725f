// Front-to-back compositing per 16x16 tile on the CPU: features (colour, depth, ...), alpha, and the
// per-pixel state the backward pass needs (final transmittance, how far the tile list was walked).
#include <vector>

#include <ATen/ATen.h>
#include <ATen/Dispatch.h>
#include <ATen/Parallel.h>

#include "gs_trainer/rasterize_backend.h"

namespace gaps::backend {
namespace {

template <typename T>
void composite_tile(int64_t tile, int tiles_x, int width, int height, int channels, const int32_t* ids,
                    const int32_t* ranges, const T* m2, const T* con, const T* opa, const T* feat, T* out_feat,
                    T* out_alpha, T* out_T, int32_t* out_n) {
  const int tx = static_cast<int>(tile % tiles_x), ty = static_cast<int>(tile / tiles_x);
  const int32_t begin = ranges[2 * tile], end = ranges[2 * tile + 1];
  std::vector<T> acc(channels);
  for (int py = ty * raster::kTileSize; py < std::min(height, (ty + 1) * raster::kTileSize); ++py) {
    for (int px = tx * raster::kTileSize; px < std::min(width, (tx + 1) * raster::kTileSize); ++px) {
      const T cx = T(px) + T(0.5), cy = T(py) + T(0.5);
      T trans = 1;
      int32_t last = 0;
      std::fill(acc.begin(), acc.end(), T(0));
      for (int32_t k = begin; k < end; ++k) {
        const int32_t g = ids[k];
        T alpha, gauss, dx, dy;
        if (!raster::eval_alpha<T>({m2[2 * g], m2[2 * g + 1]}, {con[3 * g], con[3 * g + 1], con[3 * g + 2]},
                                   opa[g], cx, cy, alpha, gauss, dx, dy))
          continue;
        const T next = trans * (1 - alpha);
        if (next < T(raster::kMinTransmittance)) break;
        const T w = alpha * trans;
        for (int ch = 0; ch < channels; ++ch) acc[ch] += w * feat[g * channels + ch];
        trans = next;
        last = k - begin + 1;
      }
      const int64_t pix = static_cast<int64_t>(py) * width + px;
      for (int ch = 0; ch < channels; ++ch) out_feat[pix * channels + ch] = acc[ch];
      out_alpha[pix] = 1 - trans;
      out_T[pix] = trans;
      out_n[pix] = last;
    }
  }
}

}  // namespace

RasterOutput rasterize_forward_cpu(const TileBins& bins, const at::Tensor& means2d_in, const at::Tensor& conics_in,
                                   const at::Tensor& opacities_in, const at::Tensor& features_in, int width,
                                   int height) {
  const auto means2d = means2d_in.contiguous(), conics = conics_in.contiguous();
  const auto opacities = opacities_in.contiguous(), features = features_in.contiguous();
  const int channels = static_cast<int>(features.size(1));
  const auto opts = features.options();
  RasterOutput out;
  out.features = at::zeros({height, width, channels}, opts);
  out.alpha = at::zeros({height, width}, opts);
  out.final_T = at::ones({height, width}, opts);
  out.n_contrib = at::zeros({height, width}, opts.dtype(at::kInt));
  const int tiles_x = (width + raster::kTileSize - 1) / raster::kTileSize;
  const int64_t num_tiles = bins.tile_ranges.size(0);
  AT_DISPATCH_FLOATING_TYPES(features.scalar_type(), "rasterize_forward_cpu", [&] {
    const int32_t* ids = bins.gaussian_ids.data_ptr<int32_t>();
    const int32_t* ranges = bins.tile_ranges.data_ptr<int32_t>();
    at::parallel_for(0, num_tiles, 1, [&](int64_t begin, int64_t end) {
      for (int64_t t = begin; t < end; ++t)
        composite_tile<scalar_t>(t, tiles_x, width, height, channels, ids, ranges, means2d.data_ptr<scalar_t>(),
                                 conics.data_ptr<scalar_t>(), opacities.data_ptr<scalar_t>(),
                                 features.data_ptr<scalar_t>(), out.features.data_ptr<scalar_t>(),
                                 out.alpha.data_ptr<scalar_t>(), out.final_T.data_ptr<scalar_t>(),
                                 out.n_contrib.data_ptr<int32_t>());
    });
  });
  return out;
}

}  // namespace gaps::backend

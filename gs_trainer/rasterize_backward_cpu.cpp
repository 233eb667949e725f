// Backward of the tile compositing on the CPU. Each tile walks its pixels back to front, so every
// (tile, Gaussian) entry is written by one thread only; entries are then summed per Gaussian, which
// keeps the result deterministic without atomics.
#include <vector>

#include <ATen/ATen.h>
#include <ATen/Dispatch.h>
#include <ATen/Parallel.h>

#include "gs_trainer/rasterize_backend.h"

namespace gaps::backend {
namespace {

// Per-entry gradient layout: mean2d (2), conic (3), opacity (1), |mean2d| (2), features (C).
constexpr int kFixed = 8;

template <typename T> struct TileInputs {
  const int32_t* ids;
  const int32_t* ranges;
  const T *m2, *con, *opa, *feat, *final_T, *g_feat, *g_alpha;
  const int32_t* n_contrib;
  int width, height, tiles_x, channels;
};

template <typename T> void backward_tile(int64_t tile, const TileInputs<T>& in, T* entry_grads) {
  const int tx = static_cast<int>(tile % in.tiles_x), ty = static_cast<int>(tile / in.tiles_x);
  const int32_t begin = in.ranges[2 * tile];
  const int C = in.channels, stride = kFixed + C;
  std::vector<T> behind(C), last_feat(C);
  for (int py = ty * raster::kTileSize; py < std::min(in.height, (ty + 1) * raster::kTileSize); ++py) {
    for (int px = tx * raster::kTileSize; px < std::min(in.width, (tx + 1) * raster::kTileSize); ++px) {
      const int64_t pix = static_cast<int64_t>(py) * in.width + px;
      const T cx = T(px) + T(0.5), cy = T(py) + T(0.5);
      const T T_final = in.final_T[pix];
      const T* gC = in.g_feat + pix * C;
      const T gA = in.g_alpha[pix];
      T trans = T_final, last_alpha = 0;
      std::fill(behind.begin(), behind.end(), T(0));
      std::fill(last_feat.begin(), last_feat.end(), T(0));
      for (int32_t k = begin + in.n_contrib[pix] - 1; k >= begin; --k) {
        const int32_t g = in.ids[k];
        const raster::Vec2<T> mean{in.m2[2 * g], in.m2[2 * g + 1]};
        const raster::Sym2<T> conic{in.con[3 * g], in.con[3 * g + 1], in.con[3 * g + 2]};
        T alpha, gauss, dx, dy;
        if (!raster::eval_alpha(mean, conic, in.opa[g], cx, cy, alpha, gauss, dx, dy)) continue;
        trans /= (1 - alpha);  // transmittance in front of this Gaussian
        const T* f = in.feat + static_cast<int64_t>(g) * C;
        T* eg = entry_grads + static_cast<int64_t>(k) * stride;
        T g_alpha = 0;
        for (int ch = 0; ch < C; ++ch) {
          behind[ch] = last_alpha * last_feat[ch] + (1 - last_alpha) * behind[ch];
          last_feat[ch] = f[ch];
          eg[kFixed + ch] += alpha * trans * gC[ch];
          g_alpha += (f[ch] - behind[ch]) * trans * gC[ch];
        }
        last_alpha = alpha;
        g_alpha += gA * T_final / (1 - alpha);  // alpha_out = 1 - prod(1 - alpha_j)
        raster::Vec2<T> g_mean;
        raster::Sym2<T> g_conic;
        T g_opacity;
        raster::eval_alpha_vjp(conic, in.opa[g], gauss, dx, dy, g_alpha, g_mean, g_conic, g_opacity);
        eg[0] += g_mean.x;
        eg[1] += g_mean.y;
        eg[2] += g_conic.a;
        eg[3] += g_conic.b;
        eg[4] += g_conic.c;
        eg[5] += g_opacity;
        eg[6] += std::abs(g_mean.x);
        eg[7] += std::abs(g_mean.y);
      }
    }
  }
}

}  // namespace

RasterGrads rasterize_backward_cpu(const TileBins& bins, const at::Tensor& means2d_in, const at::Tensor& conics_in,
                                   const at::Tensor& opacities_in, const at::Tensor& features_in,
                                   const RasterOutput& fwd, const at::Tensor& g_features_in,
                                   const at::Tensor& g_alpha_in) {
  const auto means2d = means2d_in.contiguous(), conics = conics_in.contiguous();
  const auto opacities = opacities_in.contiguous(), features = features_in.contiguous();
  const auto g_features = g_features_in.contiguous(), g_alpha = g_alpha_in.contiguous();
  const int C = static_cast<int>(features.size(1));
  const int height = static_cast<int>(fwd.alpha.size(0)), width = static_cast<int>(fwd.alpha.size(1));
  const int64_t num_entries = bins.gaussian_ids.size(0);
  at::Tensor entry_grads = at::zeros({num_entries, kFixed + C}, features.options());

  AT_DISPATCH_FLOATING_TYPES(features.scalar_type(), "rasterize_backward_cpu", [&] {
    TileInputs<scalar_t> in{bins.gaussian_ids.data_ptr<int32_t>(), bins.tile_ranges.data_ptr<int32_t>(),
                            means2d.data_ptr<scalar_t>(), conics.data_ptr<scalar_t>(),
                            opacities.data_ptr<scalar_t>(), features.data_ptr<scalar_t>(),
                            fwd.final_T.data_ptr<scalar_t>(), g_features.data_ptr<scalar_t>(),
                            g_alpha.data_ptr<scalar_t>(), fwd.n_contrib.data_ptr<int32_t>(),
                            width, height, (width + raster::kTileSize - 1) / raster::kTileSize, C};
    at::parallel_for(0, bins.tile_ranges.size(0), 1, [&](int64_t begin, int64_t end) {
      for (int64_t t = begin; t < end; ++t) backward_tile<scalar_t>(t, in, entry_grads.data_ptr<scalar_t>());
    });
  });

  const int64_t n = means2d.size(0);
  at::Tensor per_gaussian = at::zeros({n, kFixed + C}, features.options());
  per_gaussian.index_add_(0, bins.gaussian_ids.to(at::kLong), entry_grads);
  RasterGrads grads;
  grads.means2d = per_gaussian.slice(1, 0, 2).contiguous();
  grads.conics = per_gaussian.slice(1, 2, 5).contiguous();
  grads.opacities = per_gaussian.select(1, 5).contiguous();
  grads.means2d_abs = per_gaussian.slice(1, 6, 8).contiguous();
  grads.features = per_gaussian.slice(1, kFixed).contiguous();
  return grads;
}

}  // namespace gaps::backend

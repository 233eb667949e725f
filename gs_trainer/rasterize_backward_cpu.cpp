// Backward of the tile compositing on the CPU. Each tile walks its pixels back to front, so every
// (tile, Gaussian) entry is written by one thread only; entries are then summed per Gaussian, which
// keeps the result deterministic without atomics.
#include <algorithm>
#include <array>
#include <vector>

#include <ATen/ATen.h>
#include <ATen/Dispatch.h>
#include <ATen/Parallel.h>

#include "gs_trainer/cpu_parallel.h"
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

constexpr int kTilePixels = raster::kTileSize * raster::kTileSize;

// Walks the tile's list back to front (Gaussian-major, like the forward pass), undoing the compositing
// pixel by pixel: T grows back by 1 / (1 - alpha) and `behind` holds the features composited behind.
template <typename T> void backward_tile(int64_t tile, const TileInputs<T>& in, T* entry_grads) {
  const int x0 = static_cast<int>(tile % in.tiles_x) * raster::kTileSize;
  const int y0 = static_cast<int>(tile / in.tiles_x) * raster::kTileSize;
  const int tw = std::min(raster::kTileSize, in.width - x0), th = std::min(raster::kTileSize, in.height - y0);
  const int32_t begin = in.ranges[2 * tile];
  const int C = in.channels, stride = kFixed + C;
  std::array<T, kTilePixels> trans, last_alpha;
  std::array<int32_t, kTilePixels> contrib;
  std::vector<T> behind(static_cast<size_t>(kTilePixels) * C, T(0)), last_feat(behind.size(), T(0));
  int32_t max_contrib = 0;
  for (int ly = 0; ly < th; ++ly) {
    for (int lx = 0; lx < tw; ++lx) {
      const int p = ly * raster::kTileSize + lx;
      const int64_t pix = static_cast<int64_t>(y0 + ly) * in.width + x0 + lx;
      trans[p] = in.final_T[pix];
      contrib[p] = in.n_contrib[pix];
      last_alpha[p] = 0;
      max_contrib = std::max(max_contrib, contrib[p]);
    }
  }
  std::vector<T> g_feat(C);
  for (int32_t k = begin + max_contrib - 1; k >= begin; --k) {
    const int32_t g = in.ids[k];
    const raster::Vec2<T> mean{in.m2[2 * g], in.m2[2 * g + 1]};
    const raster::Sym2<T> conic{in.con[3 * g], in.con[3 * g + 1], in.con[3 * g + 2]};
    const T opacity = in.opa[g];
    const T* f = in.feat + static_cast<int64_t>(g) * C;
    T acc[kFixed] = {0, 0, 0, 0, 0, 0, 0, 0};
    std::fill(g_feat.begin(), g_feat.end(), T(0));
    bool touched = false;
    for (int ly = 0; ly < th; ++ly) {
      const T cy = T(y0 + ly) + T(0.5);
      int xb, xe;
      if (!raster::row_span(mean, conic, opacity, cy, x0, x0 + tw, xb, xe)) continue;
      for (int px = xb; px < xe; ++px) {
        const int p = ly * raster::kTileSize + (px - x0);
        if (k - begin >= contrib[p]) continue;
        T alpha, gauss, dx, dy;
        if (!raster::eval_alpha(mean, conic, opacity, T(px) + T(0.5), cy, alpha, gauss, dx, dy)) continue;
        touched = true;
        const int64_t pix = static_cast<int64_t>(y0 + ly) * in.width + px;
        const T* gC = in.g_feat + pix * C;
        trans[p] /= (1 - alpha);  // transmittance in front of this Gaussian
        const T t = trans[p];
        T* bh = behind.data() + static_cast<size_t>(p) * C;
        T* lf = last_feat.data() + static_cast<size_t>(p) * C;
        T g_alpha = 0;
        for (int ch = 0; ch < C; ++ch) {
          bh[ch] = last_alpha[p] * lf[ch] + (1 - last_alpha[p]) * bh[ch];
          lf[ch] = f[ch];
          g_feat[ch] += alpha * t * gC[ch];
          g_alpha += (f[ch] - bh[ch]) * t * gC[ch];
        }
        last_alpha[p] = alpha;
        g_alpha += in.g_alpha[pix] * in.final_T[pix] / (1 - alpha);  // alpha_out = 1 - prod(1 - alpha_j)
        raster::Vec2<T> g_mean;
        raster::Sym2<T> g_conic;
        T g_opacity;
        raster::eval_alpha_vjp(conic, opacity, gauss, dx, dy, g_alpha, g_mean, g_conic, g_opacity);
        acc[0] += g_mean.x;
        acc[1] += g_mean.y;
        acc[2] += g_conic.a;
        acc[3] += g_conic.b;
        acc[4] += g_conic.c;
        acc[5] += g_opacity;
        acc[6] += std::abs(g_mean.x);
        acc[7] += std::abs(g_mean.y);
      }
    }
    if (!touched) continue;
    T* eg = entry_grads + static_cast<int64_t>(k) * stride;
    for (int j = 0; j < kFixed; ++j) eg[j] = acc[j];
    for (int ch = 0; ch < C; ++ch) eg[kFixed + ch] = g_feat[ch];
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
    scalar_t* grads = entry_grads.data_ptr<scalar_t>();
    parallel_for_each_dynamic(bins.tile_ranges.size(0), [&](int64_t t) { backward_tile<scalar_t>(t, in, grads); });
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

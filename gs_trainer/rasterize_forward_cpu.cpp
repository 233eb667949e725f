// Front-to-back compositing per 16x16 tile on the CPU: features (colour, depth, ...), alpha, and the
// per-pixel state the backward pass needs (final transmittance, how far the tile list was walked).
// Loops run Gaussian-major over a tile's pixels, visiting in each row only the span a Gaussian can
// reach, which keeps the work proportional to real coverage.
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

constexpr int kTilePixels = raster::kTileSize * raster::kTileSize;

template <typename T> struct ForwardInputs {
  const int32_t* ids;
  const int32_t* ranges;
  const T *m2, *con, *opa, *feat;
  int width, height, tiles_x, channels;
};

template <typename T> struct ForwardOutputs {
  T *feat, *alpha, *final_T;
  int32_t* n_contrib;
};

template <typename T> void composite_tile(int64_t tile, const ForwardInputs<T>& in, const ForwardOutputs<T>& out) {
  const int x0 = static_cast<int>(tile % in.tiles_x) * raster::kTileSize;
  const int y0 = static_cast<int>(tile / in.tiles_x) * raster::kTileSize;
  const int tw = std::min(raster::kTileSize, in.width - x0), th = std::min(raster::kTileSize, in.height - y0);
  const int C = in.channels;
  std::array<T, kTilePixels> trans;
  std::array<int32_t, kTilePixels> last;
  std::array<bool, kTilePixels> done;
  std::vector<T> acc(static_cast<size_t>(kTilePixels) * C, T(0));
  trans.fill(T(1));
  last.fill(0);
  done.fill(false);
  std::array<int, raster::kTileSize> row_active;
  row_active.fill(tw);
  int active = tw * th;
  const int32_t begin = in.ranges[2 * tile], end = in.ranges[2 * tile + 1];
  for (int32_t k = begin; k < end && active > 0; ++k) {
    const int32_t g = in.ids[k];
    const raster::Vec2<T> mean{in.m2[2 * g], in.m2[2 * g + 1]};
    const raster::Sym2<T> conic{in.con[3 * g], in.con[3 * g + 1], in.con[3 * g + 2]};
    const T opacity = in.opa[g];
    const T* f = in.feat + static_cast<int64_t>(g) * C;
    for (int ly = 0; ly < th; ++ly) {
      if (row_active[ly] == 0) continue;
      const T cy = T(y0 + ly) + T(0.5);
      int xb, xe;
      if (!raster::row_span(mean, conic, opacity, cy, x0, x0 + tw, xb, xe)) continue;
      for (int px = xb; px < xe; ++px) {
        const int p = ly * raster::kTileSize + (px - x0);
        if (done[p]) continue;
        T alpha, gauss, dx, dy;
        if (!raster::eval_alpha(mean, conic, opacity, T(px) + T(0.5), cy, alpha, gauss, dx, dy)) continue;
        const T next = trans[p] * (1 - alpha);
        if (next < T(raster::kMinTransmittance)) {
          done[p] = true;
          --row_active[ly];
          --active;
          continue;
        }
        const T w = alpha * trans[p];
        T* a = acc.data() + static_cast<size_t>(p) * C;
        for (int ch = 0; ch < C; ++ch) a[ch] += w * f[ch];
        trans[p] = next;
        last[p] = k - begin + 1;
      }
    }
  }
  for (int ly = 0; ly < th; ++ly) {
    for (int lx = 0; lx < tw; ++lx) {
      const int p = ly * raster::kTileSize + lx;
      const int64_t pix = static_cast<int64_t>(y0 + ly) * in.width + x0 + lx;
      for (int ch = 0; ch < C; ++ch) out.feat[pix * C + ch] = acc[static_cast<size_t>(p) * C + ch];
      out.alpha[pix] = 1 - trans[p];
      out.final_T[pix] = trans[p];
      out.n_contrib[pix] = last[p];
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
  AT_DISPATCH_FLOATING_TYPES(features.scalar_type(), "rasterize_forward_cpu", [&] {
    const ForwardInputs<scalar_t> in{bins.gaussian_ids.data_ptr<int32_t>(), bins.tile_ranges.data_ptr<int32_t>(),
                                     means2d.data_ptr<scalar_t>(), conics.data_ptr<scalar_t>(),
                                     opacities.data_ptr<scalar_t>(), features.data_ptr<scalar_t>(), width, height,
                                     (width + raster::kTileSize - 1) / raster::kTileSize, channels};
    const ForwardOutputs<scalar_t> o{out.features.data_ptr<scalar_t>(), out.alpha.data_ptr<scalar_t>(),
                                     out.final_T.data_ptr<scalar_t>(), out.n_contrib.data_ptr<int32_t>()};
    parallel_for_each_dynamic(bins.tile_ranges.size(0), [&](int64_t t) { composite_tile<scalar_t>(t, in, o); });
  });
  return out;
}

}  // namespace gaps::backend

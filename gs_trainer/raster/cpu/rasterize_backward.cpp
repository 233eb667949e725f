// Backward of the tile compositing on the CPU. Each tile walks its pixels back to front, so every
// (tile, Gaussian) entry's gradient is written by one thread only; they are then summed per Gaussian in
// tile order, which keeps the result deterministic without atomics. The tile kernel is
// rasterize_backward_kernels.h, compiled once per instruction set (simd.h).
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

// Per-entry gradient layout: mean2d (2), conic (3), opacity (1), |mean2d| (2), features (C).
constexpr int kFixed = 8;

template <typename T>
struct BackwardArgs {
  const int32_t* ids;
  const int32_t* ranges;
  const tile::Splat<T>* splats;
  const T *feat, *final_T, *g_feat, *g_alpha;
  const int32_t* n_contrib;
  int width, height, tiles_x, channels;
  // Gradient records of the entries that touched a pixel, in their tile's slice of (number of entries) x
  // (1 + kFixed + channels): the Gaussian's id (int32 bits), then its kFixed + channels values.
  T* records;
  int32_t* record_counts;  // per tile: records at the front, records at the back of its slice
  int32_t split;           // records of Gaussians below `split` go to the front, the others to the back
};

// Hands out the record slots of one tile (see BackwardArgs::records).
template <typename T>
class TileRecords {
 public:
  TileRecords(const BackwardArgs<T>& in, int64_t tile)
      : in_(in),
        tile_(tile),
        stride_(1 + kFixed + in.channels),
        front_(in.records + static_cast<int64_t>(in.ranges[2 * tile]) * stride_),
        back_(in.records + static_cast<int64_t>(in.ranges[2 * tile + 1]) * stride_) {}

  // The kFixed + channels values of a new record for Gaussian g.
  T* add(int32_t g) {
    T* record = g < in_.split ? front_ + static_cast<int64_t>(n_front_++) * stride_
                              : back_ - static_cast<int64_t>(++n_back_) * stride_;
    std::memcpy(record, &g, sizeof(g));
    return record + 1;
  }

  void finish() {
    in_.record_counts[2 * tile_] = n_front_;
    in_.record_counts[2 * tile_ + 1] = n_back_;
  }

 private:
  const BackwardArgs<T>& in_;
  int64_t tile_;
  int stride_;
  T *front_, *back_;
  int32_t n_front_ = 0, n_back_ = 0;
};

}  // namespace
}  // namespace gaps::backend

#define GAPS_SIMD_KERNELS "gs_trainer/raster/cpu/rasterize_backward_kernels.h"
#include "gs_trainer/raster/cpu/simd_multiversion.h"
#undef GAPS_SIMD_KERNELS

namespace gaps::backend {
namespace {

// out[g] = sum of g's records, in tile order: the order of a sequential index_add_ over the entries
// (a Gaussian has at most one record per tile). The front records of every tile (Gaussians below
// `split`) and the back ones are summed by two threads, which write disjoint rows.
template <typename T>
void sum_records_per_gaussian(const BackwardArgs<T>& in, int64_t num_tiles, T* out) {
  const int values = kFixed + in.channels, stride = 1 + values;
  at::parallel_for(0, 2, 1, [&](int64_t half_begin, int64_t half_end) {
    for (int64_t half = half_begin; half < half_end; ++half) {
      for (int64_t t = 0; t < num_tiles; ++t) {
        const int32_t count = in.record_counts[2 * t + half];
        const T* record = half == 0 ? in.records + static_cast<int64_t>(in.ranges[2 * t]) * stride
                                    : in.records + static_cast<int64_t>(in.ranges[2 * t + 1] - 1) * stride;
        const int64_t step = half == 0 ? stride : -stride;
        for (int32_t j = 0; j < count; ++j, record += step) {
          int32_t g;
          std::memcpy(&g, record, sizeof(g));
          T* dst = out + static_cast<int64_t>(g) * values;
          for (int v = 0; v < values; ++v) dst[v] += record[1 + v];
        }
      }
    }
  });
}

// The gradient records of the calling thread's last backward pass: reused rather than allocated per call
// because they are large (tens of MB) and a fresh allocation costs a page fault per 4 KiB.
template <typename T>
T* record_scratch(int64_t size) {
  thread_local std::vector<T> scratch;
  if (static_cast<int64_t>(scratch.size()) < size) {
    scratch = std::vector<T>();  // release first: never hold both
    scratch.resize(static_cast<size_t>(size));
  }
  return scratch.data();
}

}  // namespace

RasterGrads rasterize_backward_cpu(const TileBins& bins, const at::Tensor& means2d_in, const at::Tensor& conics_in,
                                   const at::Tensor& opacities_in, const at::Tensor& features_in,
                                   const RasterOutput& fwd, const at::Tensor& g_features_in,
                                   const at::Tensor& g_alpha_in) {
  const auto means2d = means2d_in.contiguous(), conics = conics_in.contiguous();
  const auto opacities = opacities_in.contiguous(), features = features_in.contiguous();
  const auto g_features = g_features_in.contiguous(), g_alpha = g_alpha_in.contiguous();
  const auto final_T = fwd.final_T.contiguous(), n_contrib = fwd.n_contrib.contiguous();
  const int C = static_cast<int>(features.size(1));
  const int height = static_cast<int>(fwd.alpha.size(0)), width = static_cast<int>(fwd.alpha.size(1));
  const int64_t n = means2d.size(0), num_entries = bins.gaussian_ids.size(0);
  const int64_t num_tiles = bins.tile_ranges.size(0);
  std::vector<int32_t> record_counts(static_cast<size_t>(2 * num_tiles));
  at::Tensor per_gaussian = at::zeros({n, kFixed + C}, features.options());

  AT_DISPATCH_FLOATING_TYPES(features.scalar_type(), "rasterize_backward_cpu", [&] {
    const auto splats =
        tile::make_splats(n, means2d.data_ptr<scalar_t>(), conics.data_ptr<scalar_t>(), opacities.data_ptr<scalar_t>());
    const BackwardArgs<scalar_t> in{bins.gaussian_ids.data_ptr<int32_t>(),
                                    bins.tile_ranges.data_ptr<int32_t>(),
                                    splats.data(),
                                    features.data_ptr<scalar_t>(),
                                    final_T.data_ptr<scalar_t>(),
                                    g_features.data_ptr<scalar_t>(),
                                    g_alpha.data_ptr<scalar_t>(),
                                    n_contrib.data_ptr<int32_t>(),
                                    width,
                                    height,
                                    (width + raster::kTileSize - 1) / raster::kTileSize,
                                    C,
                                    record_scratch<scalar_t>(num_entries * (1 + kFixed + C)),
                                    record_counts.data(),
                                    static_cast<int32_t>(n / 2)};
    const auto kernel = simd::pick_for_isa(&avx512::backward_tile_entry<scalar_t>, &avx2::backward_tile_entry<scalar_t>,
                                           &baseline::backward_tile_entry<scalar_t>);
    parallel_for_each_dynamic(num_tiles, [&](int64_t t) { kernel(t, in); });
    sum_records_per_gaussian(in, num_tiles, per_gaussian.data_ptr<scalar_t>());
  });

  RasterGrads grads;
  grads.means2d = per_gaussian.slice(1, 0, 2).contiguous();
  grads.conics = per_gaussian.slice(1, 2, 5).contiguous();
  grads.opacities = per_gaussian.select(1, 5).contiguous();
  grads.means2d_abs = per_gaussian.slice(1, 6, 8).contiguous();
  grads.features = per_gaussian.slice(1, kFixed).contiguous();
  return grads;
}

}  // namespace gaps::backend

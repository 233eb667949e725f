// Tile binning on the GPU, as in 3DGS: every visible Gaussian emits one (key, index) pair per 16x16 tile
// its footprint touches (raster::tile_footprint, walked row by row by raster::for_each_footprint_tile), with
// key = tile << 32 | depth bits, and one radix sort orders the pairs by tile, then depth. The pairs are emitted in
// increasing Gaussian index and CUB's radix sort is stable, so equal depths keep increasing index: the (depth, index)
// order of cpu/bin_tiles.cpp, entry for entry.
#include <cub/device/device_radix_sort.cuh>

#include <ATen/core/Tensor.h>
#include <ATen/cuda/CUDAContext.h>
#include <ATen/ops/cat.h>
#include <ATen/ops/cumsum.h>
#include <ATen/ops/empty.h>
#include <ATen/ops/empty_like.h>
#include <ATen/ops/zeros.h>
#include <c10/cuda/CUDAGuard.h>

#include "gs_trainer/raster/rasterize_backend.h"

namespace gaps::backend {
namespace {

constexpr int kThreads = 256;

// Gaussian i's tiles (raster::tile_footprint, as cpu/bin_tiles.cpp computes them).
__device__ raster::TileFootprint tiles_of(int64_t i, const float* __restrict__ means2d,
                                          const float* __restrict__ conics, const float* __restrict__ opacities,
                                          const int32_t* __restrict__ radii, int tiles_x, int tiles_y) {
  return raster::tile_footprint<float>({means2d[2 * i], means2d[2 * i + 1]},
                                       {conics[3 * i], conics[3 * i + 1], conics[3 * i + 2]}, opacities[i], radii[i],
                                       tiles_x, tiles_y);
}

__global__ void count_tiles_kernel(int64_t n, const float* __restrict__ means2d, const float* __restrict__ conics,
                                   const float* __restrict__ opacities, const int32_t* __restrict__ radii, int tiles_x,
                                   int tiles_y, int64_t* __restrict__ counts) {
  const int64_t i = static_cast<int64_t>(blockIdx.x) * blockDim.x + threadIdx.x;
  if (i >= n) return;
  counts[i] =
      radii[i] > 0 ? raster::footprint_tile_count(tiles_of(i, means2d, conics, opacities, radii, tiles_x, tiles_y)) : 0;
}

// Gaussian i writes its counts[i] pairs at [offsets[i] - counts[i], offsets[i]) (offsets is the inclusive scan).
__global__ void emit_pairs_kernel(int64_t n, const float* __restrict__ means2d, const float* __restrict__ conics,
                                  const float* __restrict__ opacities, const int32_t* __restrict__ radii,
                                  const float* __restrict__ depths, const int64_t* __restrict__ counts,
                                  const int64_t* __restrict__ offsets, int tiles_x, int tiles_y,
                                  uint64_t* __restrict__ keys, int32_t* __restrict__ ids) {
  const int64_t i = static_cast<int64_t>(blockIdx.x) * blockDim.x + threadIdx.x;
  if (i >= n || radii[i] <= 0) return;
  const raster::TileFootprint f = tiles_of(i, means2d, conics, opacities, radii, tiles_x, tiles_y);
  // Depths are > kNearPlane > 0, and the bits of positive floats order like their values.
  const uint64_t depth_bits = __float_as_uint(depths[i]);
  int64_t k = offsets[i] - counts[i];
  raster::for_each_footprint_tile(f, [&](int tx, int ty) {
    keys[k] = (static_cast<uint64_t>(ty * tiles_x + tx) << 32) | depth_bits;
    ids[k++] = static_cast<int32_t>(i);
  });
}

// A tile's range starts where the sorted tile id changes and ends where it changes next. Tiles without
// entries keep [0, 0).
__global__ void tile_ranges_kernel(int64_t m, const uint64_t* __restrict__ keys, int32_t* __restrict__ ranges) {
  const int64_t k = static_cast<int64_t>(blockIdx.x) * blockDim.x + threadIdx.x;
  if (k >= m) return;
  const uint32_t tile = static_cast<uint32_t>(keys[k] >> 32);
  if (k == 0 || static_cast<uint32_t>(keys[k - 1] >> 32) != tile) ranges[2 * tile] = static_cast<int32_t>(k);
  if (k == m - 1 || static_cast<uint32_t>(keys[k + 1] >> 32) != tile)
    ranges[2 * tile + 1] = static_cast<int32_t>(k + 1);
}

int blocks_for(int64_t n) { return static_cast<int>((n + kThreads - 1) / kThreads); }

int bit_width(uint32_t v) {
  int bits = 0;
  while (v) {
    ++bits;
    v >>= 1;
  }
  return bits;
}

}  // namespace

namespace {

// One view's inputs, made contiguous, with its tile grid.
struct BinInput {
  at::Tensor means2d, conics, opacities, radii, depths;
  int tiles_x, tiles_y;
  int64_t size() const { return means2d.size(0); }
};

BinInput bin_input(const SplatView& v) {
  for (const auto* t : {&v.means2d, &v.conics, &v.opacities})
    TORCH_CHECK(t->is_cuda() && t->scalar_type() == at::kFloat,
                "bin_tiles_cuda: means2d, conics and opacities must be float32 CUDA tensors, got ", t->scalar_type());
  return {v.means2d.contiguous(),
          v.conics.contiguous(),
          v.opacities.contiguous(),
          v.radii.contiguous(),
          v.depths.contiguous(),
          (v.width + raster::kTileSize - 1) / raster::kTileSize,
          (v.height + raster::kTileSize - 1) / raster::kTileSize};
}

// Per Gaussian its number of tiles and their inclusive scan, whose last entry is the number of pairs.
struct PairCounts {
  at::Tensor counts, offsets;
};

PairCounts count_pairs(const BinInput& in, cudaStream_t stream) {
  const int64_t n = in.size();
  PairCounts c;
  c.counts = at::empty({n}, in.means2d.options().dtype(at::kLong));
  count_tiles_kernel<<<blocks_for(n), kThreads, 0, stream>>>(
      n, in.means2d.data_ptr<float>(), in.conics.data_ptr<float>(), in.opacities.data_ptr<float>(),
      in.radii.data_ptr<int32_t>(), in.tiles_x, in.tiles_y, c.counts.data_ptr<int64_t>());
  C10_CUDA_KERNEL_LAUNCH_CHECK();
  c.offsets = at::cumsum(c.counts, 0);
  return c;
}

// The `m` pairs of a view, emitted and sorted, as its tile bins.
TileBins emit_pairs(const BinInput& in, const PairCounts& c, int64_t m, cudaStream_t stream) {
  TORCH_CHECK(m < (int64_t{1} << 31), "bin_tiles_cuda: ", m, " tile intersections overflow the int32 tile ranges");
  const int64_t n = in.size();
  const int num_tiles = in.tiles_x * in.tiles_y;
  const auto opts = in.means2d.options();
  TileBins bins;
  bins.tile_ranges = at::zeros({num_tiles, 2}, opts.dtype(at::kInt));
  bins.gaussian_ids = at::empty({m}, opts.dtype(at::kInt));
  if (m == 0) return bins;

  at::Tensor keys = at::empty({m}, opts.dtype(at::kLong));
  at::Tensor ids = at::empty({m}, opts.dtype(at::kInt));
  auto* keys_ptr = reinterpret_cast<uint64_t*>(keys.data_ptr<int64_t>());
  emit_pairs_kernel<<<blocks_for(n), kThreads, 0, stream>>>(
      n, in.means2d.data_ptr<float>(), in.conics.data_ptr<float>(), in.opacities.data_ptr<float>(),
      in.radii.data_ptr<int32_t>(), in.depths.data_ptr<float>(), c.counts.data_ptr<int64_t>(),
      c.offsets.data_ptr<int64_t>(), in.tiles_x, in.tiles_y, keys_ptr, ids.data_ptr<int32_t>());
  C10_CUDA_KERNEL_LAUNCH_CHECK();

  // Only the bits in use are sorted: 32 of depth plus enough for the largest tile id.
  at::Tensor sorted_keys = at::empty_like(keys);
  auto* sorted_keys_ptr = reinterpret_cast<uint64_t*>(sorted_keys.data_ptr<int64_t>());
  const int end_bit = 32 + bit_width(static_cast<uint32_t>(num_tiles - 1));
  size_t temp_bytes = 0;
  C10_CUDA_CHECK(cub::DeviceRadixSort::SortPairs(nullptr, temp_bytes, keys_ptr, sorted_keys_ptr,
                                                 ids.data_ptr<int32_t>(), bins.gaussian_ids.data_ptr<int32_t>(), m, 0,
                                                 end_bit, stream));
  at::Tensor temp = at::empty({static_cast<int64_t>(temp_bytes)}, opts.dtype(at::kByte));
  C10_CUDA_CHECK(cub::DeviceRadixSort::SortPairs(temp.data_ptr(), temp_bytes, keys_ptr, sorted_keys_ptr,
                                                 ids.data_ptr<int32_t>(), bins.gaussian_ids.data_ptr<int32_t>(), m, 0,
                                                 end_bit, stream));

  tile_ranges_kernel<<<blocks_for(m), kThreads, 0, stream>>>(m, sorted_keys_ptr, bins.tile_ranges.data_ptr<int32_t>());
  C10_CUDA_KERNEL_LAUNCH_CHECK();
  return bins;
}

}  // namespace

void bin_tiles_views_cuda(const std::vector<SplatView>& views, const BinsConsumer& use) {
  if (views.empty()) return;
  const c10::cuda::CUDAGuard guard(views.front().means2d.device());
  const cudaStream_t stream = at::cuda::getCurrentCUDAStream();
  std::vector<BinInput> inputs;
  std::vector<PairCounts> counts;
  std::vector<at::Tensor> totals;
  for (const SplatView& v : views) {
    inputs.push_back(bin_input(v));
    if (inputs.back().size() == 0) {
      counts.emplace_back();
      continue;
    }
    counts.push_back(count_pairs(inputs.back(), stream));
    totals.push_back(counts.back().offsets.narrow(0, inputs.back().size() - 1, 1));
  }
  // The one host synchronisation of the pipeline, for all views together: the numbers of pairs size the sort
  // buffers.
  const at::Tensor pairs = totals.empty() ? at::Tensor() : at::cat(totals).cpu();
  for (size_t k = 0, t = 0; k < views.size(); ++k) {
    const int64_t m = inputs[k].size() == 0 ? 0 : pairs.data_ptr<int64_t>()[t++];
    use(k, emit_pairs(inputs[k], counts[k], m, stream));
  }
}

TileBins bin_tiles_cuda(const at::Tensor& means2d, const at::Tensor& conics, const at::Tensor& opacities,
                        const at::Tensor& radii, const at::Tensor& depths, int width, int height) {
  TileBins bins;
  bin_tiles_views_cuda({{means2d, conics, opacities, radii, depths, width, height}},
                       [&](size_t, TileBins b) { bins = std::move(b); });
  return bins;
}

}  // namespace gaps::backend

// Tile binning on the GPU, as in 3DGS: every visible Gaussian emits one (key, index) pair per 16x16 tile
// its footprint touches (raster::tile_footprint, walked row by row by raster::for_each_footprint_tile), with
// key = tile << 32 | depth bits, and one radix sort orders the pairs by tile, then depth. The pairs are emitted in
// increasing Gaussian index and CUB's radix sort is stable, so equal depths keep increasing index: the (depth, index)
// order of cpu/bin_tiles.cpp, entry for entry.
#include <cub/device/device_radix_sort.cuh>
#include <cub/device/device_scan.cuh>

#include <ATen/core/Tensor.h>
#include <ATen/cuda/CUDAContext.h>
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
// Rows are views of per_view Gaussians each: row i belongs to view i / per_view, whose tiles follow those of the
// views before it.
__global__ void emit_pairs_kernel(int64_t n, int64_t per_view, const float* __restrict__ means2d,
                                  const float* __restrict__ conics, const float* __restrict__ opacities,
                                  const int32_t* __restrict__ radii, const float* __restrict__ depths,
                                  const int64_t* __restrict__ counts, const int64_t* __restrict__ offsets, int tiles_x,
                                  int tiles_y, uint64_t* __restrict__ keys, int32_t* __restrict__ ids) {
  const int64_t i = static_cast<int64_t>(blockIdx.x) * blockDim.x + threadIdx.x;
  if (i >= n || radii[i] <= 0) return;
  const raster::TileFootprint f = tiles_of(i, means2d, conics, opacities, radii, tiles_x, tiles_y);
  // Depths are > kNearPlane > 0, and the bits of positive floats order like their values.
  const uint64_t depth_bits = __float_as_uint(depths[i]);
  const int64_t first_row = i / per_view * tiles_y;
  int64_t k = offsets[i] - counts[i];
  raster::for_each_footprint_tile(f, [&](int tx, int ty) {
    keys[k] = (static_cast<uint64_t>((first_row + ty) * tiles_x + tx) << 32) | depth_bits;
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

// The stacked rows of `views` views (or one), made contiguous, with one view's tile grid.
struct BinInput {
  at::Tensor means2d, conics, opacities, radii, depths;
  int views, tiles_x, tiles_y;
  int64_t size() const { return means2d.size(0); }
  int64_t num_bins() const { return int64_t{views} * tiles_x * tiles_y; }
};

BinInput bin_input(int views, const at::Tensor& means2d, const at::Tensor& conics, const at::Tensor& opacities,
                   const at::Tensor& radii, const at::Tensor& depths, int width, int height) {
  for (const auto* t : {&means2d, &conics, &opacities})
    TORCH_CHECK(t->is_cuda() && t->scalar_type() == at::kFloat,
                "bin_tiles_cuda: means2d, conics and opacities must be float32 CUDA tensors, got ", t->scalar_type());
  TORCH_CHECK(views >= 1 && means2d.size(0) % views == 0, "bin_tiles_cuda: ", means2d.size(0),
              " rows do not split into ", views, " views");
  return {means2d.contiguous(),
          conics.contiguous(),
          opacities.contiguous(),
          radii.contiguous(),
          depths.contiguous(),
          views,
          (width + raster::kTileSize - 1) / raster::kTileSize,
          (height + raster::kTileSize - 1) / raster::kTileSize};
}

TileBins bin(const BinInput& in) {
  const int64_t n = in.size();
  const auto opts = in.means2d.options();
  TORCH_CHECK(in.num_bins() < (int64_t{1} << 31), "bin_tiles_cuda: ", in.num_bins(), " tiles overflow the tile ids");
  TORCH_CHECK(n < (int64_t{1} << 31), "bin_tiles_cuda: ", n, " rows (views x Gaussians) overflow the int32 ids");
  const cudaStream_t stream = at::cuda::getCurrentCUDAStream();
  TileBins bins;
  bins.tile_ranges = at::zeros({in.num_bins(), 2}, opts.dtype(at::kInt));
  if (n == 0) {
    bins.gaussian_ids = at::empty({0}, opts.dtype(at::kInt));
    return bins;
  }
  at::Tensor counts = at::empty({n}, opts.dtype(at::kLong));
  count_tiles_kernel<<<blocks_for(n), kThreads, 0, stream>>>(
      n, in.means2d.data_ptr<float>(), in.conics.data_ptr<float>(), in.opacities.data_ptr<float>(),
      in.radii.data_ptr<int32_t>(), in.tiles_x, in.tiles_y, counts.data_ptr<int64_t>());
  C10_CUDA_KERNEL_LAUNCH_CHECK();
  // CUB's scan called here rather than through at::cumsum, whose dispatch cost the host more than the scan costs the
  // GPU in every training step.
  at::Tensor offsets = at::empty_like(counts);
  size_t scan_bytes = 0;
  C10_CUDA_CHECK(cub::DeviceScan::InclusiveSum(nullptr, scan_bytes, counts.data_ptr<int64_t>(),
                                               offsets.data_ptr<int64_t>(), n, stream));
  const at::Tensor scan_temp = at::empty({static_cast<int64_t>(scan_bytes)}, opts.dtype(at::kByte));
  C10_CUDA_CHECK(cub::DeviceScan::InclusiveSum(scan_temp.data_ptr(), scan_bytes, counts.data_ptr<int64_t>(),
                                               offsets.data_ptr<int64_t>(), n, stream));
  // The one host synchronisation of the pipeline (for all views together): the number of pairs sizes the sort
  // buffers.
  const int64_t m = offsets[n - 1].item<int64_t>();
  TORCH_CHECK(m < (int64_t{1} << 31), "bin_tiles_cuda: ", m, " tile intersections overflow the int32 tile ranges");
  bins.gaussian_ids = at::empty({m}, opts.dtype(at::kInt));
  if (m == 0) return bins;

  at::Tensor keys = at::empty({m}, opts.dtype(at::kLong));
  at::Tensor ids = at::empty({m}, opts.dtype(at::kInt));
  auto* keys_ptr = reinterpret_cast<uint64_t*>(keys.data_ptr<int64_t>());
  emit_pairs_kernel<<<blocks_for(n), kThreads, 0, stream>>>(
      n, n / in.views, in.means2d.data_ptr<float>(), in.conics.data_ptr<float>(), in.opacities.data_ptr<float>(),
      in.radii.data_ptr<int32_t>(), in.depths.data_ptr<float>(), counts.data_ptr<int64_t>(),
      offsets.data_ptr<int64_t>(), in.tiles_x, in.tiles_y, keys_ptr, ids.data_ptr<int32_t>());
  C10_CUDA_KERNEL_LAUNCH_CHECK();

  // Only the bits in use are sorted: 32 of depth plus enough for the largest tile id.
  at::Tensor sorted_keys = at::empty_like(keys);
  auto* sorted_keys_ptr = reinterpret_cast<uint64_t*>(sorted_keys.data_ptr<int64_t>());
  const int end_bit = 32 + bit_width(static_cast<uint32_t>(in.num_bins() - 1));
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

TileBins bin_tiles_views_cuda(int views, const at::Tensor& means2d, const at::Tensor& conics,
                              const at::Tensor& opacities, const at::Tensor& radii, const at::Tensor& depths, int width,
                              int height) {
  const c10::cuda::CUDAGuard guard(means2d.device());
  return bin(bin_input(views, means2d, conics, opacities, radii, depths, width, height));
}

TileBins bin_tiles_cuda(const at::Tensor& means2d, const at::Tensor& conics, const at::Tensor& opacities,
                        const at::Tensor& radii, const at::Tensor& depths, int width, int height) {
  return bin_tiles_views_cuda(1, means2d, conics, opacities, radii, depths, width, height);
}

}  // namespace gaps::backend

// Backward of the tile compositing on the GPU, as in gsplat: one 16x16 thread block per tile, one thread
// per pixel, walking the tile's list back to front in shared-memory batches. Each thread undoes its
// pixel's compositing (T grows back by 1 / (1 - alpha), `behind` holds the features composited behind)
// with the operations of cpu/rasterize_backward.cpp. The 32 pixels of a warp then sum their gradients for
// the current Gaussian, all slots at once (slot_sums: a butterfly that halves the slots each lane carries at
// every step, 16 shuffles for 16 slots where one warp sum per slot takes 60), which leaves slot s in lane
// s * 32 / slots; those lanes add their sums to the per-Gaussian gradients with one atomic instruction
// between them. Tiles start longest list first (longest_first_kernel). The |mean2d| sums are compiled in only where a
// caller asks for them (absolute-gradient densification). The variants measured against this form are in
// docs/benchmarks.md ("CUDA rasterizer against gsplat", "Speed: ..."). Float atomics make the last bits of a gradient
// depend on the order warps finish (relative ~1e-7); a deterministic order would need per-(tile, Gaussian) partial sums
// plus a second sort, far from cheap at millions of intersections. This file alone is compiled with FMA contraction:
// its gradients are float sums in another order than the CPU's anyway, and the alpha decisions it must share with the
// forward pass come from gaussian_power, which is written with unfused intrinsics.
#include <ATen/core/Tensor.h>
#include <ATen/cuda/CUDAContext.h>
#include <ATen/ops/empty.h>
#include <ATen/ops/zeros.h>
#include <c10/cuda/CUDAGuard.h>

#include "gs_trainer/raster/cuda/cuda_common.h"
#include "gs_trainer/raster/rasterize_backend.h"

namespace gaps::backend {
namespace {

constexpr int kTile = raster::kTileSize;
constexpr int kBlock = kTile * kTile;
constexpr int kWarps = kBlock / 32;
constexpr unsigned kFullMask = 0xffffffffu;

// One butterfly step of slot_sums: lanes whose OFFSET bit is set keep the upper HALF of their slots, the
// others the lower half, each adding what its partner lane OFFSET away sends of the same half.
template <int HALF, int OFFSET, int P>
__device__ __forceinline__ void halve_slots(float (&v)[P], int lane) {
  const bool upper = (lane & OFFSET) != 0;
#pragma unroll
  for (int i = 0; i < HALF; ++i) {
    const float send = upper ? v[i] : v[i + HALF];
    const float keep = upper ? v[i + HALF] : v[i];
    v[i] = keep + __shfl_xor_sync(kFullMask, send, OFFSET);
  }
  if constexpr (HALF > 1) halve_slots<HALF / 2, OFFSET / 2>(v, lane);
}

// The sums over the warp's 32 lanes of each of the P slots (P a power of two, at most 32): slot
// lane / (32 / P) is returned in that lane, every lane of a group of 32 / P holding the same sum.
template <int P>
__device__ __forceinline__ float slot_sums(float (&v)[P], int lane) {
  static_assert(P >= 2 && P <= 32 && (P & (P - 1)) == 0, "slot_sums takes 2, 4, 8, 16 or 32 slots");
  halve_slots<P / 2, 16>(v, lane);
  float sum = v[0];
#pragma unroll
  for (int offset = 16 / P; offset > 0; offset /= 2) sum += __shfl_xor_sync(kFullMask, sum, offset);
  return sum;
}

constexpr int padded_slots(int n) {
  int p = 2;
  while (p < n) p *= 2;
  return p;
}

// The gradient slots of one Gaussian.
enum Slot { kMeanX, kMeanY, kConicA, kConicB, kConicC, kOpacity, kAbsX, kAbsY, kFeatures };

// The largest n_contrib of the block: entries past it were walked by no pixel of the tile.
__device__ int block_max(int v, int* s_warp) {
  for (int offset = 16; offset > 0; offset /= 2) v = max(v, __shfl_xor_sync(kFullMask, v, offset));
  const int thread = threadIdx.y * kTile + threadIdx.x;
  if (thread % 32 == 0) s_warp[thread / 32] = v;
  __syncthreads();
  int m = s_warp[0];
  for (int w = 1; w < kWarps; ++w) m = max(m, s_warp[w]);
  return m;
}

struct BackwardArgs : CompositeInputs {
  const int32_t* __restrict__ tile_order;  // block b composites tile tile_order[b]
  const float* __restrict__ final_T;
  const int32_t* __restrict__ n_contrib;
  const float* __restrict__ g_out_features;  // H x W x C
  const float* __restrict__ g_out_alpha;     // H x W
  float* __restrict__ g_means2d;             // N x 2
  float* __restrict__ g_conics;              // N x 3
  float* __restrict__ g_opacities;           // N
  float* __restrict__ g_features;            // N x C
  float* __restrict__ g_means2d_abs;         // N x 2
};

// Where a lane adds the sum of its gradient slot: base + g * stride for Gaussian g. A lane's slot is fixed for the
// whole kernel, so this is worked out once; base is nullptr for lanes that add nothing (the other lanes holding
// the same slot, padding slots past the channels, the |mean2d| slots unless ABS).
struct SlotTarget {
  float* base = nullptr;
  int stride = 0;
};

template <bool ABS>
__device__ SlotTarget slot_target(const BackwardArgs& a, int slot) {
  if (slot < kConicA) return {a.g_means2d + (slot - kMeanX), 2};
  if (slot < kOpacity) return {a.g_conics + (slot - kConicA), 3};
  if (slot == kOpacity) return {a.g_opacities, 1};
  if (slot < kFeatures) return ABS ? SlotTarget{a.g_means2d_abs + (slot - kAbsX), 2} : SlotTarget{};
  if (slot - kFeatures < a.channels) return {a.g_features + (slot - kFeatures), a.channels};
  return {};
}

// The tiles, longest lists first (to within 9 %: eight buckets per doubling of the length). Blocks start in
// launch order, so the last blocks to start, those that run while the other SMs fall idle, are the short ones:
// 768 tiles (504x378) take 1.2 waves of 660 blocks, and in that order the second wave's tail is the shortest
// tiles' instead of whichever came last in the image. One block; the order within a bucket is arbitrary.
constexpr int kOrderBuckets = 256;
constexpr int kOrderThreads = 1024;

__device__ int length_bucket(const int32_t* ranges, int tile) {
  const int n = ranges[2 * tile + 1] - ranges[2 * tile];
  return min(kOrderBuckets - 1, __float2int_rd(8.f * __log2f(static_cast<float>(n) + 1.f)));
}

__global__ void __launch_bounds__(kOrderThreads)
    longest_first_kernel(int tiles, const int32_t* __restrict__ ranges, int32_t* __restrict__ order) {
  __shared__ int s_next[kOrderBuckets];
  for (int b = threadIdx.x; b < kOrderBuckets; b += kOrderThreads) s_next[b] = 0;
  __syncthreads();
  for (int t = threadIdx.x; t < tiles; t += kOrderThreads) atomicAdd(&s_next[length_bucket(ranges, t)], 1);
  __syncthreads();
  if (threadIdx.x == 0) {  // each bucket's first position, the longest bucket at 0
    int start = 0;
    for (int b = kOrderBuckets - 1; b >= 0; --b) {
      const int count = s_next[b];
      s_next[b] = start;
      start += count;
    }
  }
  __syncthreads();
  for (int t = threadIdx.x; t < tiles; t += kOrderThreads) order[atomicAdd(&s_next[length_bucket(ranges, t)], 1)] = t;
}

// ABS: also sum the absolute 2D-mean gradients (only absolute-gradient densification asks for them).
template <int CMAX, bool ABS>
__global__ void __launch_bounds__(kBlock) rasterize_backward_kernel(BackwardArgs a) {
  const int tile = a.tile_order[blockIdx.x];
  const int px = (tile % a.tiles_x) * kTile + threadIdx.x, py = (tile / a.tiles_x) * kTile + threadIdx.y;
  const int thread = threadIdx.y * kTile + threadIdx.x;
  const int lane = thread % 32;
  const bool inside = px < a.width && py < a.height;
  const float cx = static_cast<float>(px) + 0.5f, cy = static_cast<float>(py) + 0.5f;

  __shared__ int s_id[kBlock];
  __shared__ StagedSplat s_splat[kBlock];
  __shared__ __align__(16) float s_feat[kBlock * CMAX];
  __shared__ int s_warp[kWarps];

  // The pixel's forward state and output gradients.
  const int64_t pix = static_cast<int64_t>(py) * a.width + px;
  const float final_T = inside ? a.final_T[pix] : 1.f;
  const int contrib = inside ? a.n_contrib[pix] : 0;
  float g_out[CMAX];
  for (int ch = 0; ch < CMAX; ++ch)
    g_out[ch] = inside && ch < a.channels ? a.g_out_features[pix * a.channels + ch] : 0.f;
  const float g_out_alpha = inside ? a.g_out_alpha[pix] : 0.f;
  float T = final_T;
  float last_alpha = 0.f;
  float behind[CMAX], last_feat[CMAX];
  for (int ch = 0; ch < CMAX; ++ch) behind[ch] = last_feat[ch] = 0.f;

  constexpr int kSlots = padded_slots(kFeatures + CMAX);
  constexpr int kLanesPerSlot = 32 / kSlots;
  const SlotTarget target = lane % kLanesPerSlot == 0 ? slot_target<ABS>(a, lane / kLanesPerSlot) : SlotTarget{};

  const int begin = a.ranges[2 * tile];
  const int max_contrib = block_max(contrib, s_warp);
  for (int batch_end = begin + max_contrib; batch_end > begin; batch_end -= kBlock) {
    __syncthreads();  // the previous batch is consumed
    // Staged back to front: slot j holds entry batch_end - 1 - j.
    const int k = batch_end - 1 - thread;
    if (k >= begin) {
      const int g = a.ids[k];
      s_id[thread] = g;
      s_splat[thread] = stage_splat(a, g);
      for (int ch = 0; ch < CMAX; ++ch)
        s_feat[thread * CMAX + ch] = ch < a.channels ? a.features[static_cast<int64_t>(g) * a.channels + ch] : 0.f;
    }
    __syncthreads();
    const int batch = min(kBlock, batch_end - begin);
    // Every lane runs every iteration (the bounds are block-uniform), so the warp shuffles below are safe.
    for (int j = 0; j < batch; ++j) {
      const int entry = batch_end - 1 - j - begin;  // position in the tile's list
      const StagedSplat splat = s_splat[j];
      const float opacity = splat.conic_c_opacity.y;
      float alpha = 0.f, gauss = 0.f, dx = 0.f, dy = 0.f;
      bool valid = false;
      if (entry < contrib) {
        const float power = staged_power(splat, cx, cy, dx, dy);
        valid =
            power >= splat.conic_c_opacity.z && raster::alpha_from_power_host_rounding(power, opacity, alpha, gauss);
      }
      if (!__any_sync(kFullMask, valid)) continue;
      float slots[kSlots];
#pragma unroll
      for (int i = 0; i < kSlots; ++i) slots[i] = 0.f;
      if (valid) {
        const float inv_one_minus_alpha = __frcp_rn(1.f - alpha);  // 1 / (1 - alpha), rounded alike
        T *= inv_one_minus_alpha;                                  // transmittance in front of this Gaussian
        const float t = T;
        const float* f = s_feat + j * CMAX;
        float g_alpha = 0.f;
#pragma unroll
        for (int ch = 0; ch < CMAX; ++ch) {
          behind[ch] = last_alpha * last_feat[ch] + (1 - last_alpha) * behind[ch];
          last_feat[ch] = f[ch];
          slots[kFeatures + ch] = alpha * t * g_out[ch];
          g_alpha += (f[ch] - behind[ch]) * t * g_out[ch];
        }
        last_alpha = alpha;
        g_alpha += g_out_alpha * final_T * inv_one_minus_alpha;  // alpha_out = 1 - prod(1 - alpha_j)
        raster::Vec2<float> g_mean;
        raster::Sym2<float> g_conic;
        float g_opacity;
        const raster::Sym2<float> conic{splat.mean_conic_ab.z, splat.mean_conic_ab.w, splat.conic_c_opacity.x};
        raster::eval_alpha_vjp(conic, opacity, gauss, dx, dy, g_alpha, g_mean, g_conic, g_opacity);
        slots[kMeanX] = g_mean.x;
        slots[kMeanY] = g_mean.y;
        slots[kConicA] = g_conic.a;
        slots[kConicB] = g_conic.b;
        slots[kConicC] = g_conic.c;
        slots[kOpacity] = g_opacity;
        if (ABS) {
          slots[kAbsX] = fabsf(g_mean.x);
          slots[kAbsY] = fabsf(g_mean.y);
        }
      }
      const float sum = slot_sums(slots, lane);
      if (target.base != nullptr) atomicAdd(target.base + static_cast<int64_t>(s_id[j]) * target.stride, sum);
    }
  }
}

}  // namespace

RasterGrads rasterize_backward_cuda(const TileBins& bins, const at::Tensor& means2d_in, const at::Tensor& conics_in,
                                    const at::Tensor& opacities_in, const at::Tensor& features_in,
                                    const RasterOutput& fwd, const at::Tensor& g_features_in,
                                    const at::Tensor& g_alpha_in, bool absolute_grads) {
  check_raster_inputs({&means2d_in, &conics_in, &opacities_in, &features_in, &g_features_in, &g_alpha_in});
  const c10::cuda::CUDAGuard guard(means2d_in.device());
  const auto means2d = means2d_in.contiguous(), conics = conics_in.contiguous();
  const auto opacities = opacities_in.contiguous(), features = features_in.contiguous();
  const auto g_features = g_features_in.contiguous(), g_alpha = g_alpha_in.contiguous();
  const auto final_T = fwd.final_T.contiguous(), n_contrib = fwd.n_contrib.contiguous();
  const auto ranges = bins.tile_ranges.contiguous(), ids = bins.gaussian_ids.contiguous();
  const int channels = static_cast<int>(features.size(1));
  const int height = static_cast<int>(fwd.alpha.size(0)), width = static_cast<int>(fwd.alpha.size(1));
  const int64_t n = means2d.size(0);
  const auto opts = features.options();

  // The gradients are contiguous blocks of one zeroed buffer: one allocation and one fill per step instead of five.
  const int64_t columns = 2 + 3 + 1 + channels + (absolute_grads ? 2 : 0);
  const at::Tensor zeroed = at::zeros({n * columns}, opts);
  int64_t used = 0;
  const auto block = [&](int64_t cols) {
    at::Tensor t = zeroed.narrow(0, used, n * cols).view({n, cols});
    used += n * cols;
    return t;
  };
  RasterGrads grads;
  grads.means2d = block(2);
  grads.conics = block(3);
  grads.opacities = block(1).view({n});
  grads.features = block(channels);
  if (absolute_grads) grads.means2d_abs = block(2);
  if (n == 0) return grads;

  const int tiles_x = (width + kTile - 1) / kTile, tiles_y = (height + kTile - 1) / kTile;
  const int tiles = tiles_x * tiles_y;
  const at::Tensor tile_order = at::empty({tiles}, ranges.options());
  const auto stream = at::cuda::getCurrentCUDAStream();
  longest_first_kernel<<<1, kOrderThreads, 0, stream>>>(tiles, ranges.data_ptr<int32_t>(),
                                                        tile_order.data_ptr<int32_t>());
  C10_CUDA_KERNEL_LAUNCH_CHECK();
  const BackwardArgs args{composite_inputs(width, height, tiles_x, ranges, ids, means2d, conics, opacities, features),
                          tile_order.data_ptr<int32_t>(),
                          final_T.data_ptr<float>(),
                          n_contrib.data_ptr<int32_t>(),
                          g_features.data_ptr<float>(),
                          g_alpha.data_ptr<float>(),
                          grads.means2d.data_ptr<float>(),
                          grads.conics.data_ptr<float>(),
                          grads.opacities.data_ptr<float>(),
                          grads.features.data_ptr<float>(),
                          absolute_grads ? grads.means2d_abs.data_ptr<float>() : nullptr};
  dispatch_channels(channels, [&](auto cmax) {
    const dim3 grid(tiles), block(kTile, kTile);
    if (absolute_grads)
      rasterize_backward_kernel<decltype(cmax)::value, true><<<grid, block, 0, stream>>>(args);
    else
      rasterize_backward_kernel<decltype(cmax)::value, false><<<grid, block, 0, stream>>>(args);
  });
  C10_CUDA_KERNEL_LAUNCH_CHECK();
  return grads;
}

}  // namespace gaps::backend

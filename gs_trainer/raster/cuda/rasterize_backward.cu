// Backward of the tile compositing on the GPU, as in gsplat: one 16x16 thread block per tile, one thread
// per pixel, walking the tile's list back to front in shared-memory batches. Each thread undoes its
// pixel's compositing (T grows back by 1 / (1 - alpha), `behind` holds the features composited behind)
// with the operations of cpu/rasterize_backward.cpp. The entries that composited at some pixel of a warp are
// gathered, as many as fill 32 gradient slots (three at 3 channels), and the 32 pixels then sum all slots at once
// (slot_sums: a butterfly that halves the slots each lane carries at every step, 31 shuffles in 5 dependent steps
// for 32 slots), which leaves slot s in lane s; the lanes add their sums to the per-Gaussian gradients with one
// atomic instruction between them. The |mean2d| sums are compiled in only where a caller asks for them
// (absolute-gradient densification). The variants measured against this form are in docs/benchmarks.md ("CUDA
// rasterizer against gsplat", "Speed: ...").
// Float atomics make the last bits of a gradient depend on the order warps finish (relative ~1e-7); a
// deterministic order would need per-(tile, Gaussian) partial sums plus a second sort, far from cheap at
// millions of intersections. This file alone is compiled with FMA contraction: its gradients are float
// sums in another order than the CPU's anyway, and the alpha decisions it must share with the forward
// pass come from gaussian_power, which is written with unfused intrinsics.
#include <ATen/core/Tensor.h>
#include <ATen/cuda/CUDAContext.h>
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

// The sums over the warp's 32 lanes of each of the 32 slots: lane l returns slot l's.
__device__ __forceinline__ float slot_sums(float (&v)[32], int lane) {
  halve_slots<16, 16>(v, lane);
  return v[0];
}

// The gradient slots of one Gaussian: its 2D mean, conic and opacity, the |mean2d| sums where asked for, then
// one per feature channel.
enum Slot { kMeanX, kMeanY, kConicA, kConicB, kConicC, kOpacity, kAbsX, kAbsY };
template <bool ABS>
constexpr int kFirstFeature = ABS ? kAbsY + 1 : kAbsX;
template <int CMAX, bool ABS>
constexpr int kEntrySlots = kFirstFeature<ABS> + CMAX;
// The entries one 32-slot butterfly sums at once: 3 at up to 4 channels, 2 with the |mean2d| sums, 1 at 16.
template <int CMAX, bool ABS>
constexpr int kEntriesPerSum = 32 / kEntrySlots<CMAX, ABS>;

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

// Where the sum of a gradient slot goes; nullptr for padding slots past the channels.
template <bool ABS>
__device__ float* slot_target(const BackwardArgs& a, int64_t g, int slot) {
  if (slot < kConicA) return a.g_means2d + 2 * g + (slot - kMeanX);
  if (slot < kOpacity) return a.g_conics + 3 * g + (slot - kConicA);
  if (slot == kOpacity) return a.g_opacities + g;
  if (ABS && slot < kFirstFeature<ABS>) return a.g_means2d_abs + 2 * g + (slot - kAbsX);
  const int ch = slot - kFirstFeature<ABS>;
  return ch < a.channels ? a.g_features + g * a.channels + ch : nullptr;
}

// Whether an entry composited at the pixel, and the terms its gradients need.
struct EntryHit {
  float alpha = 0.f, gauss = 0.f, dx = 0.f, dy = 0.f;
  bool valid = false;
};

// `walked`: the entry is among the pixel's n_contrib (the forward pass stopped before the others).
__device__ __forceinline__ EntryHit hit_test(const StagedSplat& splat, float cx, float cy, bool walked) {
  EntryHit h;
  if (walked) {
    const float power = staged_power(splat, cx, cy, h.dx, h.dy);
    h.valid = power >= splat.conic_c_opacity.z &&
              raster::alpha_from_power_host_rounding(power, splat.conic_c_opacity.y, h.alpha, h.gauss);
  }
  return h;
}

// The pixel's forward state and output gradients, and what undoing its compositing back to front carries.
template <int CMAX, bool ABS>
struct PixelWalk {
  float final_T, g_out_alpha;
  float g_out[CMAX];
  float T, last_alpha;
  float behind[CMAX], last_feat[CMAX];  // features composited behind the current entry; the previous entry's

  // Undoes one entry that composited at the pixel (T grows back by 1 / (1 - alpha)) and writes its gradients
  // into slots [OFFSET, OFFSET + kEntrySlots).
  template <int OFFSET>
  __device__ __forceinline__ void undo(float (&slots)[32], const StagedSplat& splat, const float* f,
                                       const EntryHit& h) {
    const float inv_one_minus_alpha = 1.f / (1.f - h.alpha);
    T *= inv_one_minus_alpha;  // transmittance in front of this Gaussian
    float g_alpha = 0.f;
#pragma unroll
    for (int ch = 0; ch < CMAX; ++ch) {
      behind[ch] = last_alpha * last_feat[ch] + (1 - last_alpha) * behind[ch];
      last_feat[ch] = f[ch];
      slots[OFFSET + kFirstFeature<ABS> + ch] = h.alpha * T * g_out[ch];
      g_alpha += (f[ch] - behind[ch]) * T * g_out[ch];
    }
    last_alpha = h.alpha;
    g_alpha += g_out_alpha * final_T * inv_one_minus_alpha;  // alpha_out = 1 - prod(1 - alpha_j)
    raster::Vec2<float> g_mean;
    raster::Sym2<float> g_conic;
    float g_opacity;
    const raster::Sym2<float> conic{splat.mean_conic_ab.z, splat.mean_conic_ab.w, splat.conic_c_opacity.x};
    raster::eval_alpha_vjp(conic, splat.conic_c_opacity.y, h.gauss, h.dx, h.dy, g_alpha, g_mean, g_conic, g_opacity);
    slots[OFFSET + kMeanX] = g_mean.x;
    slots[OFFSET + kMeanY] = g_mean.y;
    slots[OFFSET + kConicA] = g_conic.a;
    slots[OFFSET + kConicB] = g_conic.b;
    slots[OFFSET + kConicC] = g_conic.c;
    slots[OFFSET + kOpacity] = g_opacity;
    if constexpr (ABS) {
      slots[OFFSET + kAbsX] = fabsf(g_mean.x);
      slots[OFFSET + kAbsY] = fabsf(g_mean.y);
    }
  }

  // undo into the slots of the group's entry k (K: the first candidate; the offsets must be constants for the
  // slots to stay in registers).
  template <int K = 0>
  __device__ __forceinline__ void undo_as(int k, float (&slots)[32], const StagedSplat& splat, const float* f,
                                          const EntryHit& h) {
    constexpr int kPer = kEntrySlots<CMAX, ABS>;
    if constexpr ((K + 1) * kPer <= 32) {
      if (k == K)
        undo<K * kPer>(slots, splat, f, h);
      else
        undo_as<K + 1>(k, slots, splat, f, h);
    }
  }
};

// ABS: also sum the absolute 2D-mean gradients (only absolute-gradient densification asks for them).
// The entries that composited somewhere in the warp are gathered kEntriesPerSum at a time into 32 slots, and one
// butterfly and one atomic instruction of the whole warp sum and add them: at 3 channels three entries take 31
// shuffles in 5 dependent steps, where one entry alone took 16.
template <int CMAX, bool ABS>
__global__ void __launch_bounds__(kBlock) rasterize_backward_kernel(BackwardArgs a) {
  const int tile = blockIdx.y * a.tiles_x + blockIdx.x;
  const int px = blockIdx.x * kTile + threadIdx.x, py = blockIdx.y * kTile + threadIdx.y;
  const int thread = threadIdx.y * kTile + threadIdx.x;
  const int lane = thread % 32;
  const bool inside = px < a.width && py < a.height;
  const float cx = static_cast<float>(px) + 0.5f, cy = static_cast<float>(py) + 0.5f;

  __shared__ int s_id[kBlock];
  __shared__ StagedSplat s_splat[kBlock];
  __shared__ __align__(16) float s_feat[kBlock * CMAX];
  __shared__ int s_warp[kWarps];

  const int64_t pix = static_cast<int64_t>(py) * a.width + px;
  PixelWalk<CMAX, ABS> walk;
  walk.final_T = inside ? a.final_T[pix] : 1.f;
  walk.g_out_alpha = inside ? a.g_out_alpha[pix] : 0.f;
  for (int ch = 0; ch < CMAX; ++ch) {
    walk.g_out[ch] = inside && ch < a.channels ? a.g_out_features[pix * a.channels + ch] : 0.f;
    walk.behind[ch] = walk.last_feat[ch] = 0.f;
  }
  walk.T = walk.final_T;
  walk.last_alpha = 0.f;
  const int contrib = inside ? a.n_contrib[pix] : 0;

  constexpr int kPer = kEntrySlots<CMAX, ABS>;
  constexpr int kGroup = kEntriesPerSum<CMAX, ABS>;
  static_assert(kGroup >= 1, "one entry's gradient slots must fit a warp");
  float slots[32];
#pragma unroll
  for (int i = 0; i < 32; ++i) slots[i] = 0.f;
  int group[kGroup] = {};  // the Gaussians of the gathered entries
  int filled = 0;          // entries gathered; the same in every lane of the warp
  // The butterfly leaves slot l in lane l: slot l % kPer of the group's entry l / kPer.
  const auto add_group = [&] {
    const float sum = slot_sums(slots, lane);
    const int k = lane / kPer;
    int g = group[0];
#pragma unroll
    for (int i = 1; i < kGroup; ++i)
      if (k == i) g = group[i];
    if (k < filled) {
      float* target = slot_target<ABS>(a, g, lane % kPer);
      if (target != nullptr) atomicAdd(target, sum);
    }
#pragma unroll
    for (int i = 0; i < 32; ++i) slots[i] = 0.f;
    filled = 0;
  };

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
    const int last = batch_end - 1 - begin;  // position in the tile's list of slot 0
    // Every lane runs every iteration (the bounds are block-uniform), so the warp shuffles are safe.
    for (int j = 0; j < batch; ++j) {
      const EntryHit h = hit_test(s_splat[j], cx, cy, last - j < contrib);
      if (!__any_sync(kFullMask, h.valid)) continue;
      if (h.valid) walk.undo_as(filled, slots, s_splat[j], s_feat + j * CMAX, h);
#pragma unroll
      for (int i = 0; i < kGroup; ++i)
        if (i == filled) group[i] = s_id[j];
      if (++filled == kGroup) add_group();
    }
  }
  if (filled > 0) add_group();
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
  const BackwardArgs args{composite_inputs(width, height, tiles_x, ranges, ids, means2d, conics, opacities, features),
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
    const dim3 grid(tiles_x, tiles_y), block(kTile, kTile);
    const auto stream = at::cuda::getCurrentCUDAStream();
    if (absolute_grads)
      rasterize_backward_kernel<decltype(cmax)::value, true><<<grid, block, 0, stream>>>(args);
    else
      rasterize_backward_kernel<decltype(cmax)::value, false><<<grid, block, 0, stream>>>(args);
  });
  C10_CUDA_KERNEL_LAUNCH_CHECK();
  return grads;
}

}  // namespace gaps::backend

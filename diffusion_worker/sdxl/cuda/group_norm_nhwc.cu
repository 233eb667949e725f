// GroupNorm over channels-last activations in three launches: partial moments per (sample, pixel chunk, group),
// each channel's fused scale and shift from them, then one elementwise pass (with SiLU when asked).
#include <ATen/Dispatch.h>
#include <ATen/core/Tensor.h>
#include <ATen/cuda/CUDAContext.h>
#include <ATen/ops/empty.h>
#include <ATen/ops/empty_like.h>
#include <c10/cuda/CUDAGuard.h>
#include <c10/util/BFloat16.h>
#include <c10/util/Half.h>

#include <cstdint>

#include "diffusion_worker/sdxl/cuda/group_norm_nhwc_cuda.h"

namespace gaps::sdxl {
namespace {

constexpr int kApplyThreads = 256;

// The value each group's moments are taken about: its first channel at the sample's first pixel.
template <typename T>
__device__ float group_shift(const T* x, int64_t n, int64_t pixels, int64_t channels, int64_t group_size, int64_t g) {
  return static_cast<float>(x[n * pixels * channels + g * group_size]);
}

template <typename T, int kVec>
struct alignas(sizeof(T) * kVec) Pack {
  T v[kVec];
};

// Block (chunk, n) sums v - shift and (v - shift)^2 over its pixels for every group: partial[n][chunk][g][2]. A
// thread reads kVec neighbouring channels of a pixel at once (16 bytes where the channels allow) for the pixels
// of its row and keeps per-channel sums; the rows' sums meet in shared memory and each group's are added in a
// fixed order, so the result does not depend on the threads' timing (a CUDA graph's replay gives the eager run's
// values; float atomics would not).
template <typename T, int kVec>
__global__ void group_moments_kernel(const T* __restrict__ x, int64_t pixels, int64_t channels, int64_t groups,
                                     int64_t pixels_per_chunk, float* __restrict__ partial) {
  extern __shared__ float shared[];  // shifts[groups], then rows x channels x {s1, s2}
  float* shifts = shared;
  float* channel_sums = shared + groups;
  const int64_t n = blockIdx.y, chunk = blockIdx.x, chunks = gridDim.x;
  const int64_t group_size = channels / groups, columns = channels / kVec;
  const int thread = threadIdx.y * blockDim.x + threadIdx.x, threads = blockDim.x * blockDim.y;
  for (int64_t g = thread; g < groups; g += threads) shifts[g] = group_shift(x, n, pixels, channels, group_size, g);
  __syncthreads();
  const int64_t begin = chunk * pixels_per_chunk;
  const int64_t end = begin + pixels_per_chunk < pixels ? begin + pixels_per_chunk : pixels;
  const auto* sample = reinterpret_cast<const Pack<T, kVec>*>(x + n * pixels * channels);
  for (int64_t column = threadIdx.x; column < columns; column += blockDim.x) {
    float shift[kVec], s1[kVec], s2[kVec];
#pragma unroll
    for (int k = 0; k < kVec; ++k) {
      shift[k] = shifts[(column * kVec + k) / group_size];
      s1[k] = s2[k] = 0.f;
    }
    for (int64_t p = begin + threadIdx.y; p < end; p += blockDim.y) {
      const Pack<T, kVec> v = sample[p * columns + column];
#pragma unroll
      for (int k = 0; k < kVec; ++k) {
        const float d = static_cast<float>(v.v[k]) - shift[k];
        s1[k] += d;
        s2[k] += d * d;
      }
    }
    float* out = channel_sums + 2 * (threadIdx.y * channels + column * kVec);
#pragma unroll
    for (int k = 0; k < kVec; ++k) {
      out[2 * k] = s1[k];
      out[2 * k + 1] = s2[k];
    }
  }
  __syncthreads();
  for (int64_t g = thread; g < groups; g += threads) {
    float g1 = 0.f, g2 = 0.f;
    for (unsigned row = 0; row < blockDim.y; ++row) {
      const float* sums = channel_sums + 2 * (row * channels + g * group_size);
      for (int64_t c = 0; c < group_size; ++c) {
        g1 += sums[2 * c];
        g2 += sums[2 * c + 1];
      }
    }
    float* out = partial + ((n * chunks + chunk) * groups + g) * 2;
    out[0] = g1;
    out[1] = g2;
  }
}

// One thread per (n, c): scale = weight * rstd and offset = bias - mean * scale of its group, so that the
// normalised value is x * scale + offset (ATen's fused parameters).
template <typename T>
__global__ void group_scale_offset_kernel(const T* __restrict__ x, const float* __restrict__ partial, int64_t samples,
                                          int64_t pixels, int64_t channels, int64_t groups, int64_t chunks, float eps,
                                          const float* __restrict__ weight, const float* __restrict__ bias,
                                          float* __restrict__ scale, float* __restrict__ offset) {
  const int64_t i = static_cast<int64_t>(blockIdx.x) * blockDim.x + threadIdx.x;
  if (i >= samples * channels) return;
  const int64_t n = i / channels, c = i % channels, group_size = channels / groups, g = c / group_size;
  double s1 = 0, s2 = 0;
  for (int64_t k = 0; k < chunks; ++k) {
    const float* p = partial + ((n * chunks + k) * groups + g) * 2;
    s1 += p[0];
    s2 += p[1];
  }
  const double count = static_cast<double>(pixels * group_size);
  const double shifted_mean = s1 / count;
  const double var = fmax(s2 / count - shifted_mean * shifted_mean, 0.0);
  const double mean = group_shift(x, n, pixels, channels, group_size, g) + shifted_mean;
  const float rstd = static_cast<float>(rsqrt(var + static_cast<double>(eps)));
  scale[i] = weight[c] * rstd;
  offset[i] = bias[c] - static_cast<float>(mean) * scale[i];
}

// y = x * scale + offset per channel (then SiLU), kVec neighbouring channels of one pixel per thread.
template <typename T, int kVec>
__global__ void group_apply_kernel(const T* __restrict__ x, int64_t total, int64_t pixels, int64_t channels,
                                   const float* __restrict__ scale, const float* __restrict__ offset, bool silu,
                                   T* __restrict__ y) {
  const int64_t packs = total / kVec;
  for (int64_t i = static_cast<int64_t>(blockIdx.x) * blockDim.x + threadIdx.x; i < packs;
       i += static_cast<int64_t>(gridDim.x) * blockDim.x) {
    const int64_t e = i * kVec, c0 = e % channels, n = e / (pixels * channels);
    const float* s = scale + n * channels + c0;
    const float* o = offset + n * channels + c0;
    Pack<T, kVec> in = reinterpret_cast<const Pack<T, kVec>*>(x)[i], out;
#pragma unroll
    for (int k = 0; k < kVec; ++k) {
      float v = static_cast<float>(in.v[k]) * s[k] + o[k];
      if (silu) v = v / (1.f + __expf(-v));
      out.v[k] = static_cast<T>(v);
    }
    reinterpret_cast<Pack<T, kVec>*>(y)[i] = out;
  }
}

int64_t ceil_div(int64_t a, int64_t b) { return (a + b - 1) / b; }

// The three kernels over x with kVec channels per load.
template <typename T, int kVec>
void launch(const at::Tensor& x, int64_t groups, const at::Tensor& weight, const at::Tensor& bias, double eps,
            bool silu, at::Tensor& y) {
  const int64_t samples = x.size(0), channels = x.size(1), pixels = x.size(2) * x.size(3);
  const cudaStream_t stream = at::cuda::getCurrentCUDAStream();
  const int sms = at::cuda::getCurrentDeviceProperties()->multiProcessorCount;
  // About four blocks per multiprocessor over the batch, each of at least 32 pixels.
  const int64_t chunks =
      std::max<int64_t>(1, std::min(ceil_div(pixels, 32), ceil_div(static_cast<int64_t>(sms) * 4, samples)));
  const int64_t pixels_per_chunk = ceil_div(pixels, chunks);
  const auto float_options = x.options().dtype(at::kFloat);
  at::Tensor partial = at::empty({samples, chunks, groups, 2}, float_options);
  at::Tensor scale = at::empty({samples, channels}, float_options), offset = at::empty_like(scale);
  // A row of threads across the channels' columns, as many rows as fit in 256 threads.
  const int64_t columns = channels / kVec;
  const unsigned block_x = static_cast<unsigned>(std::min<int64_t>(columns, 256));
  const dim3 moments_block(block_x, std::max(1u, 256u / block_x));
  const dim3 moments_grid(static_cast<unsigned>(chunks), static_cast<unsigned>(samples));
  const size_t shared_bytes = (groups + 2 * moments_block.y * channels) * sizeof(float);
  TORCH_CHECK(shared_bytes <= 48 * 1024, "group_norm_nhwc: ", channels, " channels need ", shared_bytes,
              " bytes of shared memory, more than 48 KiB");
  group_moments_kernel<T, kVec><<<moments_grid, moments_block, shared_bytes, stream>>>(
      x.const_data_ptr<T>(), pixels, channels, groups, pixels_per_chunk, partial.mutable_data_ptr<float>());
  C10_CUDA_KERNEL_LAUNCH_CHECK();
  group_scale_offset_kernel<T>
      <<<static_cast<unsigned>(ceil_div(samples * channels, kApplyThreads)), kApplyThreads, 0, stream>>>(
          x.const_data_ptr<T>(), partial.const_data_ptr<float>(), samples, pixels, channels, groups, chunks,
          static_cast<float>(eps), weight.const_data_ptr<float>(), bias.const_data_ptr<float>(),
          scale.mutable_data_ptr<float>(), offset.mutable_data_ptr<float>());
  C10_CUDA_KERNEL_LAUNCH_CHECK();
  const int64_t packs = x.numel() / kVec;
  const int64_t blocks = std::min<int64_t>(ceil_div(packs, kApplyThreads), static_cast<int64_t>(sms) * 8);
  group_apply_kernel<T, kVec><<<static_cast<unsigned>(blocks), kApplyThreads, 0, stream>>>(
      x.const_data_ptr<T>(), x.numel(), pixels, channels, scale.const_data_ptr<float>(), offset.const_data_ptr<float>(),
      silu, y.mutable_data_ptr<T>());
  C10_CUDA_KERNEL_LAUNCH_CHECK();
}

}  // namespace

at::Tensor group_norm_nhwc_cuda(const at::Tensor& x, int64_t groups, const at::Tensor& weight_in,
                                const at::Tensor& bias_in, double eps, bool silu) {
  TORCH_CHECK(x.is_cuda() && x.dim() == 4 && x.is_contiguous(at::MemoryFormat::ChannelsLast),
              "group_norm_nhwc: a 4-d channels-last CUDA tensor expected, got ", x.sizes(), " on ", x.device());
  const int64_t channels = x.size(1);
  TORCH_CHECK(groups > 0 && channels % groups == 0, "group_norm_nhwc: ", channels, " channels in ", groups, " groups");
  TORCH_CHECK(weight_in.defined() && bias_in.defined() && weight_in.numel() == channels && bias_in.numel() == channels,
              "group_norm_nhwc: weight and bias of ", channels, " values expected");
  const c10::cuda::CUDAGuard guard(x.device());
  at::Tensor y = at::empty_like(x, x.options(), at::MemoryFormat::ChannelsLast);
  if (x.numel() == 0) return y;
  const auto float_options = x.options().dtype(at::kFloat);
  const at::Tensor weight = weight_in.to(float_options).contiguous(), bias = bias_in.to(float_options).contiguous();
  AT_DISPATCH_FLOATING_TYPES_AND2(at::kHalf, at::kBFloat16, x.scalar_type(), "group_norm_nhwc", [&] {
    constexpr int kVec = 16 / sizeof(scalar_t);  // 16-byte loads and stores
    const auto aligned = [](const at::Tensor& t) { return reinterpret_cast<uintptr_t>(t.const_data_ptr()) % 16 == 0; };
    if (channels % kVec == 0 && aligned(x) && aligned(y))
      launch<scalar_t, kVec>(x, groups, weight, bias, eps, silu, y);
    else
      launch<scalar_t, 1>(x, groups, weight, bias, eps, silu, y);
  });
  return y;
}

}  // namespace gaps::sdxl

// The render statistics of a batch of candidate renders in one kernel: per pixel the luma (Rec. 601, in the
// order and float rounding of greyscale(), no FMA), its grey level, the entropy of its clipped 3×3 window's level
// histogram (local_entropy_map), alpha and coverage; per image the sums in double, reduced per block and added
// atomically. It replaces some twenty ATen launches per batch (the one-hot codes alone are 16 float channels per
// pixel, pooled), which cost a fifth of a pool's scoring time.
#include <algorithm>
#include <cmath>

#include <ATen/core/Tensor.h>
#include <ATen/cuda/CUDAContext.h>
#include <ATen/ops/zeros.h>
#include <c10/cuda/CUDAGuard.h>

#include "gs_trainer/gaps/cuda/render_statistics_cuda.h"

namespace gaps::backend {
namespace {

constexpr int kThreads = 256;
constexpr int kSums = 5;  // alpha, entropy, covered, luma, luma²

struct StatsArgs {
  const float* __restrict__ rgb;  // B×H×W pixels of `stride` floats, red, green, blue first
  int stride;
  const float* __restrict__ alpha;  // B×H×W
  int height, width, bins;
  float threshold;
  float log2_max;             // log2(min(9, bins)), the most a window's entropy reaches
  double* __restrict__ sums;  // B×kSums
};

__device__ float luma_at(const float* __restrict__ rgb, int stride, int64_t pixel) {
  const float r = fminf(fmaxf(rgb[stride * pixel], 0.f), 1.f);
  const float g = fminf(fmaxf(rgb[stride * pixel + 1], 0.f), 1.f);
  const float b = fminf(fmaxf(rgb[stride * pixel + 2], 0.f), 1.f);
  return 0.299f * r + 0.587f * g + 0.114f * b;
}

__device__ int level_of(float luma, int bins) {
  const float l = floorf(luma * static_cast<float>(bins));
  return static_cast<int>(fminf(fmaxf(l, 0.f), static_cast<float>(bins - 1)));
}

// Normalised Shannon entropy of the levels in the in-image part of the 3×3 window around (x, y) of image `image`.
__device__ float window_entropy(const StatsArgs& a, int64_t image, int x, int y) {
  int level[9];
  int n = 0;
  for (int dy = -1; dy <= 1; ++dy) {
    for (int dx = -1; dx <= 1; ++dx) {
      const int xx = x + dx, yy = y + dy;
      if (xx < 0 || yy < 0 || xx >= a.width || yy >= a.height) continue;
      level[n++] = level_of(luma_at(a.rgb, a.stride, (image * a.height + yy) * a.width + xx), a.bins);
    }
  }
  float bits = 0.f;
  for (int j = 0; j < n; ++j) {
    bool first = true;
    int count = 0;
    for (int k = 0; k < n; ++k) {
      count += level[k] == level[j];
      first = first && !(k < j && level[k] == level[j]);
    }
    if (!first) continue;  // each level once
    const float p = static_cast<float>(count) / static_cast<float>(n);
    bits -= p * logf(p);
  }
  return bits / 0.693147180559945309f / a.log2_max;
}

// Grid: x over the pixels of one image, y over the images.
__global__ void render_statistics_kernel(StatsArgs a) {
  const int64_t image = blockIdx.y;
  const int64_t pixels = static_cast<int64_t>(a.height) * a.width;
  const int64_t p = static_cast<int64_t>(blockIdx.x) * blockDim.x + threadIdx.x;
  double v[kSums] = {0, 0, 0, 0, 0};
  if (p < pixels) {
    const int x = static_cast<int>(p % a.width), y = static_cast<int>(p / a.width);
    const float alpha = a.alpha[image * pixels + p];
    const float luma = luma_at(a.rgb, a.stride, image * pixels + p);
    v[0] = alpha;
    v[1] = window_entropy(a, image, x, y);
    v[2] = alpha >= a.threshold ? 1.0 : 0.0;
    v[3] = luma;
    v[4] = static_cast<double>(luma) * static_cast<double>(luma);
  }
  __shared__ double partial[kSums][kThreads / 32];
  const int lane = threadIdx.x % 32, warp = threadIdx.x / 32;
  for (int s = 0; s < kSums; ++s) {
    double x = v[s];
    for (int offset = 16; offset > 0; offset /= 2) x += __shfl_down_sync(0xffffffffu, x, offset);
    if (lane == 0) partial[s][warp] = x;
  }
  __syncthreads();
  if (threadIdx.x < kSums) {
    double total = 0;
    for (int w = 0; w < kThreads / 32; ++w) total += partial[threadIdx.x][w];
    atomicAdd(&a.sums[image * kSums + threadIdx.x], total);
  }
}

}  // namespace

at::Tensor render_statistics_sums_cuda(const at::Tensor& images_in, const at::Tensor& alphas_in, int bins,
                                       double coverage_threshold) {
  TORCH_CHECK(images_in.is_cuda() && images_in.scalar_type() == at::kFloat && alphas_in.is_cuda() &&
                  alphas_in.scalar_type() == at::kFloat,
              "render_statistics_cuda: float32 CUDA images and alphas expected");
  TORCH_CHECK(bins >= 2, "entropy needs at least 2 bins, got ", bins);
  const c10::cuda::CUDAGuard guard(images_in.device());
  // The first three channels of contiguous B×H×W×C renders are read in place (no copy of the batch).
  const bool packed_pixels = images_in.stride(3) == 1 && images_in.stride(2) >= 3 &&
                             images_in.stride(1) == images_in.size(2) * images_in.stride(2) &&
                             images_in.stride(0) == images_in.size(1) * images_in.stride(1);
  const at::Tensor images = packed_pixels ? images_in : images_in.contiguous();
  const at::Tensor alphas = alphas_in.contiguous();
  const int64_t count = images.size(0);
  const int height = static_cast<int>(images.size(1)), width = static_cast<int>(images.size(2));
  const int64_t pixels = static_cast<int64_t>(height) * width;
  at::Tensor sums = at::zeros({count, kSums}, images.options().dtype(at::kDouble));
  if (count == 0 || pixels == 0) return sums;
  TORCH_CHECK(count < 65536, "render_statistics_cuda: at most 65535 images at once, got ", count);
  const StatsArgs args{images.data_ptr<float>(),
                       static_cast<int>(images.stride(2)),
                       alphas.data_ptr<float>(),
                       height,
                       width,
                       bins,
                       static_cast<float>(coverage_threshold),
                       static_cast<float>(std::log2(static_cast<double>(std::min(9, bins)))),
                       sums.data_ptr<double>()};
  const dim3 grid(static_cast<unsigned>((pixels + kThreads - 1) / kThreads), static_cast<unsigned>(count));
  render_statistics_kernel<<<grid, kThreads, 0, at::cuda::getCurrentCUDAStream()>>>(args);
  C10_CUDA_KERNEL_LAUNCH_CHECK();
  return sums;
}

}  // namespace gaps::backend

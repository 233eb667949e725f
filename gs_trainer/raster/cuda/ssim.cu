// The SSIM map and its backward pass on the GPU: one thread per (pixel, channel) and pass, running
// ssim_math.h as cpu/ssim.cpp does. Four kernels in all replace the ~100 ATen launches (convolutions,
// element-wise products, their autograd nodes) of the same computation in tensor operations. The training loss
// runs the same passes with its own sums folded in: the map's pass also sums the weighted |pred - gt| and
// 1 - SSIM of its block (one atomic per block), and the backward forms dL/dS from dL/dloss on the fly and adds the
// L1 term's gradient where it writes the prediction's; a dozen ATen launches and their host work fewer per step.
#include <ATen/core/Tensor.h>
#include <ATen/cuda/CUDAContext.h>
#include <ATen/ops/empty.h>
#include <ATen/ops/empty_like.h>
#include <ATen/ops/zeros.h>
#include <c10/cuda/CUDAGuard.h>

#include "gs_trainer/raster/cuda/cuda_common.h"
#include "gs_trainer/raster/ssim_backend.h"
#include "gs_trainer/raster/ssim_math.h"

namespace gaps::backend {
namespace {

struct Element {
  int y, x, c;
  int64_t i;
};

__device__ bool element_at(const ssim::Shape& s, Element& e) {
  e.i = static_cast<int64_t>(blockIdx.x) * blockDim.x + threadIdx.x;
  if (e.i >= int64_t(s.height) * s.width * s.channels) return false;
  e.c = static_cast<int>(e.i % s.channels);
  const int64_t pixel = e.i / s.channels;
  e.x = static_cast<int>(pixel % s.width);
  e.y = static_cast<int>(pixel / s.width);
  return true;
}

__global__ void moments_kernel(const float* __restrict__ pred, const float* __restrict__ gt, ssim::Shape s,
                               ssim::Window<float> win, float* __restrict__ rows) {
  Element e;
  if (!element_at(s, e)) return;
  ssim::horizontal_moments(pred, gt, s, win, e.y, e.x, e.c, rows + e.i * ssim::kMoments);
}

__global__ void map_kernel(const float* __restrict__ rows, ssim::Shape s, ssim::Window<float> win,
                           float* __restrict__ map, float* __restrict__ partials) {
  Element e;
  if (!element_at(s, e)) return;
  float m[ssim::kMoments];
  ssim::vertical_pass<float, ssim::kMoments>(rows, s, win, e.y, e.x, e.c, m);
  map[e.i] = ssim::ssim_value_and_partials(m, partials + e.i * ssim::kPartials);
}

constexpr unsigned kFullMask = 0xffffffffu;
constexpr int kWarps = kElementwiseThreads / 32;

// The loss's per-element weight: weight[pixel] (H x W x 1), or 1.
__device__ __forceinline__ float loss_weight(const float* __restrict__ weight, int64_t i, int channels) {
  return weight != nullptr ? weight[i / channels] : 1.f;
}

// The SSIM map's pass of the training loss: the partials as map_kernel writes them, and the block's sums of
// w * |pred - gt| and w * (1 - S) added to sums[0] and sums[1].
__global__ void __launch_bounds__(kElementwiseThreads)
    loss_map_kernel(const float* __restrict__ rows, ssim::Shape s, ssim::Window<float> win,
                    const float* __restrict__ pred, const float* __restrict__ gt, const float* __restrict__ weight,
                    float* __restrict__ partials, float* __restrict__ sums) {
  Element e;
  float l1 = 0.f, dssim = 0.f;
  if (element_at(s, e)) {
    float m[ssim::kMoments];
    ssim::vertical_pass<float, ssim::kMoments>(rows, s, win, e.y, e.x, e.c, m);
    const float value = ssim::ssim_value_and_partials(m, partials + e.i * ssim::kPartials);
    const float w = loss_weight(weight, e.i, s.channels);
    l1 = w * fabsf(pred[e.i] - gt[e.i]);
    dssim = w * (1.f - value);
  }
  for (int offset = 16; offset > 0; offset /= 2) {
    l1 += __shfl_xor_sync(kFullMask, l1, offset);
    dssim += __shfl_xor_sync(kFullMask, dssim, offset);
  }
  __shared__ float s_sums[2][kWarps];
  const int warp = threadIdx.x / 32;
  if (threadIdx.x % 32 == 0) {
    s_sums[0][warp] = l1;
    s_sums[1][warp] = dssim;
  }
  __syncthreads();
  if (threadIdx.x < 2) {
    float total = 0.f;
    for (int w = 0; w < kWarps; ++w) total += s_sums[threadIdx.x][w];
    atomicAdd(sums + threadIdx.x, total);
  }
}

__global__ void loss_value_kernel(const float* __restrict__ sums, float inv_n, float lambda, float* __restrict__ loss) {
  *loss = ((1.f - lambda) * sums[0] + lambda * sums[1]) * inv_n;
}

// dL/dS of the training loss at element i: -lambda / n * w * dL/dloss.
struct LossMapGradient {
  const float* g_loss;
  const float* weight;
  float scale;  // -lambda / n
  int channels;
  __device__ float operator()(int64_t i) const { return *g_loss * scale * loss_weight(weight, i, channels); }
};

ssim::Shape shape_of(const at::Tensor& image) {
  return {static_cast<int>(image.size(0)), static_cast<int>(image.size(1)), static_cast<int>(image.size(2))};
}

// The L1 term's gradient of the training loss, (1 - lambda) / n * w * dL/dloss * sign(pred - gt).
struct L1Gradient {
  const float* g_loss;
  const float* weight;
  float scale;  // (1 - lambda) / n
  int channels;
  __device__ float operator()(int64_t i, float pred, float gt) const {
    const float diff = pred - gt;
    const float sign = diff > 0.f ? 1.f : (diff < 0.f ? -1.f : 0.f);
    return *g_loss * scale * loss_weight(weight, i, channels) * sign;
  }
};

// The plain SSIM backward adds nothing.
struct NoExtraGradient {
  __device__ float operator()(int64_t, float, float) const { return 0.f; }
};

template <typename MapGradient>
__global__ void gradient_rows_kernel(const float* __restrict__ partials, MapGradient g_map, ssim::Shape s,
                                     ssim::Window<float> win, float* __restrict__ rows) {
  Element e;
  if (!element_at(s, e)) return;
  ssim::horizontal_gradient(partials, g_map, s, win, e.y, e.x, e.c, rows + e.i * ssim::kPartials);
}

template <typename ExtraGradient>
__global__ void prediction_gradient_kernel(const float* __restrict__ rows, const float* __restrict__ pred,
                                           const float* __restrict__ gt, ssim::Shape s, ssim::Window<float> win,
                                           ExtraGradient extra, float* __restrict__ g_pred) {
  Element e;
  if (!element_at(s, e)) return;
  float b[ssim::kPartials];
  ssim::vertical_pass<float, ssim::kPartials>(rows, s, win, e.y, e.x, e.c, b);
  g_pred[e.i] = ssim::prediction_gradient(b, pred[e.i], gt[e.i]) + extra(e.i, pred[e.i], gt[e.i]);
}

// dL/dpred through the SSIM passes for dL/dS = g_map(i), plus extra(i, pred, gt) per element; pred, gt and
// partials contiguous on the current device.
template <typename MapGradient, typename ExtraGradient>
at::Tensor ssim_gradient(const at::Tensor& pred, const at::Tensor& gt, const at::Tensor& partials,
                         const MapGradient& g_map, const ExtraGradient& extra) {
  const ssim::Shape s = shape_of(pred);
  const auto win = ssim::gaussian_window<float>();
  at::Tensor g_pred = at::empty_like(pred);
  const int64_t n = pred.numel();
  if (n == 0) return g_pred;
  at::Tensor rows = at::empty({s.height, s.width, s.channels, ssim::kPartials}, pred.options());
  const auto stream = at::cuda::getCurrentCUDAStream();
  gradient_rows_kernel<<<blocks_for(n), kElementwiseThreads, 0, stream>>>(partials.data_ptr<float>(), g_map, s, win,
                                                                          rows.data_ptr<float>());
  C10_CUDA_KERNEL_LAUNCH_CHECK();
  prediction_gradient_kernel<<<blocks_for(n), kElementwiseThreads, 0, stream>>>(
      rows.data_ptr<float>(), pred.data_ptr<float>(), gt.data_ptr<float>(), s, win, extra, g_pred.data_ptr<float>());
  C10_CUDA_KERNEL_LAUNCH_CHECK();
  return g_pred;
}

}  // namespace

SsimForward ssim_forward_cuda(const at::Tensor& pred_in, const at::Tensor& gt_in) {
  check_cuda_float("pred", pred_in);
  check_cuda_float("gt", gt_in);
  const c10::cuda::CUDAGuard guard(pred_in.device());
  const auto pred = pred_in.contiguous(), gt = gt_in.contiguous();
  const ssim::Shape s = shape_of(pred);
  const auto win = ssim::gaussian_window<float>();
  SsimForward out;
  out.map = at::empty_like(pred);
  out.partials = at::empty({s.height, s.width, s.channels, ssim::kPartials}, pred.options());
  const int64_t n = pred.numel();
  if (n == 0) return out;
  at::Tensor rows = at::empty({s.height, s.width, s.channels, ssim::kMoments}, pred.options());
  const auto stream = at::cuda::getCurrentCUDAStream();
  moments_kernel<<<blocks_for(n), kElementwiseThreads, 0, stream>>>(pred.data_ptr<float>(), gt.data_ptr<float>(), s,
                                                                    win, rows.data_ptr<float>());
  C10_CUDA_KERNEL_LAUNCH_CHECK();
  map_kernel<<<blocks_for(n), kElementwiseThreads, 0, stream>>>(
      rows.data_ptr<float>(), s, win, out.map.data_ptr<float>(), out.partials.data_ptr<float>());
  C10_CUDA_KERNEL_LAUNCH_CHECK();
  return out;
}

at::Tensor ssim_backward_cuda(const at::Tensor& pred_in, const at::Tensor& gt_in, const at::Tensor& partials_in,
                              const at::Tensor& g_map_in) {
  check_cuda_float("pred", pred_in);
  check_cuda_float("g_map", g_map_in);
  const c10::cuda::CUDAGuard guard(pred_in.device());
  const auto g_map = g_map_in.contiguous();
  return ssim_gradient(pred_in.contiguous(), gt_in.contiguous(), partials_in.contiguous(),
                       ssim::MapGradientArray<float>{g_map.data_ptr<float>()}, NoExtraGradient{});
}

namespace {

// The loss's weight as a pointer into a contiguous H x W x 1 float tensor on pred's device, or nullptr.
const float* weight_pointer(const at::Tensor& weight, const at::Tensor& pred, at::Tensor& holder) {
  if (!weight.defined()) return nullptr;
  check_cuda_float("weight", weight);
  TORCH_CHECK(weight.numel() == pred.size(0) * pred.size(1), "the loss weight must be H x W x 1 = ", pred.size(0),
              " x ", pred.size(1), " x 1, got ", weight.sizes());
  holder = weight.contiguous();
  return holder.data_ptr<float>();
}

}  // namespace

PhotometricForward photometric_forward_cuda(const at::Tensor& pred_in, const at::Tensor& gt_in,
                                            const at::Tensor& weight_in, double lambda) {
  check_cuda_float("pred", pred_in);
  check_cuda_float("gt", gt_in);
  const c10::cuda::CUDAGuard guard(pred_in.device());
  const auto pred = pred_in.contiguous(), gt = gt_in.contiguous();
  at::Tensor weight;
  const float* w = weight_pointer(weight_in, pred, weight);
  const ssim::Shape s = shape_of(pred);
  const auto win = ssim::gaussian_window<float>();
  const int64_t n = pred.numel();
  PhotometricForward out;
  out.partials = at::empty({s.height, s.width, s.channels, ssim::kPartials}, pred.options());
  out.loss = at::empty({}, pred.options());
  at::Tensor sums = at::zeros({2}, pred.options());
  const auto stream = at::cuda::getCurrentCUDAStream();
  if (n > 0) {
    at::Tensor rows = at::empty({s.height, s.width, s.channels, ssim::kMoments}, pred.options());
    moments_kernel<<<blocks_for(n), kElementwiseThreads, 0, stream>>>(pred.data_ptr<float>(), gt.data_ptr<float>(), s,
                                                                      win, rows.data_ptr<float>());
    C10_CUDA_KERNEL_LAUNCH_CHECK();
    loss_map_kernel<<<blocks_for(n), kElementwiseThreads, 0, stream>>>(
        rows.data_ptr<float>(), s, win, pred.data_ptr<float>(), gt.data_ptr<float>(), w, out.partials.data_ptr<float>(),
        sums.data_ptr<float>());
    C10_CUDA_KERNEL_LAUNCH_CHECK();
  }
  // An empty image's loss is 0 / 0, NaN, as the mean of no elements.
  loss_value_kernel<<<1, 1, 0, stream>>>(sums.data_ptr<float>(), n > 0 ? 1.f / static_cast<float>(n) : NAN,
                                         static_cast<float>(lambda), out.loss.data_ptr<float>());
  C10_CUDA_KERNEL_LAUNCH_CHECK();
  return out;
}

at::Tensor photometric_backward_cuda(const at::Tensor& pred_in, const at::Tensor& gt_in, const at::Tensor& partials_in,
                                     const at::Tensor& weight_in, double lambda, const at::Tensor& g_loss_in) {
  check_cuda_float("pred", pred_in);
  check_cuda_float("dL/dloss", g_loss_in);
  TORCH_CHECK(g_loss_in.numel() == 1, "the loss gradient must be one value, got ", g_loss_in.sizes());
  const c10::cuda::CUDAGuard guard(pred_in.device());
  const auto pred = pred_in.contiguous(), g_loss = g_loss_in.contiguous();
  at::Tensor weight;
  const float* w = weight_pointer(weight_in, pred, weight);
  const int channels = static_cast<int>(pred.size(2));
  const float inv_n = pred.numel() > 0 ? 1.f / static_cast<float>(pred.numel()) : 0.f;
  const float* g = g_loss.data_ptr<float>();
  return ssim_gradient(pred, gt_in.contiguous(), partials_in.contiguous(),
                       LossMapGradient{g, w, -static_cast<float>(lambda) * inv_n, channels},
                       L1Gradient{g, w, static_cast<float>(1 - lambda) * inv_n, channels});
}

}  // namespace gaps::backend

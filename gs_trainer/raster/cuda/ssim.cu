// The SSIM map and its backward pass on the GPU: one thread per (pixel, channel) and pass, running
// ssim_math.h as cpu/ssim.cpp does. Four kernels in all replace the ~100 ATen launches (convolutions,
// element-wise products, their autograd nodes) of the same computation in tensor operations.
#include <ATen/core/Tensor.h>
#include <ATen/cuda/CUDAContext.h>
#include <ATen/ops/empty.h>
#include <ATen/ops/empty_like.h>
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

__global__ void gradient_rows_kernel(const float* __restrict__ partials, const float* __restrict__ g_map, ssim::Shape s,
                                     ssim::Window<float> win, float* __restrict__ rows) {
  Element e;
  if (!element_at(s, e)) return;
  ssim::horizontal_gradient(partials, g_map, s, win, e.y, e.x, e.c, rows + e.i * ssim::kPartials);
}

__global__ void prediction_gradient_kernel(const float* __restrict__ rows, const float* __restrict__ pred,
                                           const float* __restrict__ gt, ssim::Shape s, ssim::Window<float> win,
                                           float* __restrict__ g_pred) {
  Element e;
  if (!element_at(s, e)) return;
  float b[ssim::kPartials];
  ssim::vertical_pass<float, ssim::kPartials>(rows, s, win, e.y, e.x, e.c, b);
  g_pred[e.i] = ssim::prediction_gradient(b, pred[e.i], gt[e.i]);
}

ssim::Shape shape_of(const at::Tensor& image) {
  return {static_cast<int>(image.size(0)), static_cast<int>(image.size(1)), static_cast<int>(image.size(2))};
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
  const auto pred = pred_in.contiguous(), gt = gt_in.contiguous(), partials = partials_in.contiguous();
  const auto g_map = g_map_in.contiguous();
  const ssim::Shape s = shape_of(pred);
  const auto win = ssim::gaussian_window<float>();
  at::Tensor g_pred = at::empty_like(pred);
  const int64_t n = pred.numel();
  if (n == 0) return g_pred;
  at::Tensor rows = at::empty({s.height, s.width, s.channels, ssim::kPartials}, pred.options());
  const auto stream = at::cuda::getCurrentCUDAStream();
  gradient_rows_kernel<<<blocks_for(n), kElementwiseThreads, 0, stream>>>(
      partials.data_ptr<float>(), g_map.data_ptr<float>(), s, win, rows.data_ptr<float>());
  C10_CUDA_KERNEL_LAUNCH_CHECK();
  prediction_gradient_kernel<<<blocks_for(n), kElementwiseThreads, 0, stream>>>(
      rows.data_ptr<float>(), pred.data_ptr<float>(), gt.data_ptr<float>(), s, win, g_pred.data_ptr<float>());
  C10_CUDA_KERNEL_LAUNCH_CHECK();
  return g_pred;
}

}  // namespace gaps::backend

// PatchMatch's steps on the GPU: a kernel per step, one thread per pixel (of one colour for the updates),
// each running the same patchmatch_math.h function as the CPU loop.
#include <ATen/cuda/CUDAContext.h>
#include <c10/cuda/CUDAException.h>

#include "gs_trainer/init/patchmatch_backend.h"

namespace gaps::pm {
namespace {

constexpr int kThreads = 128;

unsigned int blocks_for(int64_t n) { return static_cast<unsigned int>((n + kThreads - 1) / kThreads); }

__device__ bool any_pixel(const Problem& p, int* x, int* y) {
  const int64_t i = static_cast<int64_t>(blockIdx.x) * blockDim.x + threadIdx.x;
  if (i >= static_cast<int64_t>(p.cam.width) * p.cam.height) return false;
  *x = static_cast<int>(i % p.cam.width);
  *y = static_cast<int>(i / p.cam.width);
  return true;
}

__global__ void init_kernel(const Problem p) {
  int x, y;
  if (any_pixel(p, &x, &y)) init_pixel(p, x, y);
}

__global__ void update_kernel(const Problem p, int colour, int iteration) {
  const int64_t k = static_cast<int64_t>(blockIdx.x) * blockDim.x + threadIdx.x;
  const int64_t slots = static_cast<int64_t>((p.cam.width + 1) / 2) * p.cam.height;
  int x, y;
  if (k < slots && checkerboard_pixel(p.cam.width, colour, static_cast<int>(k), &x, &y))
    update_pixel(p, x, y, iteration);
}

__global__ void rescore_kernel(const Problem p) {
  int x, y;
  if (any_pixel(p, &x, &y)) rescore_pixel(p, x, y);
}

__global__ void filter_kernel(const Problem p) {
  int x, y;
  if (any_pixel(p, &x, &y)) filter_pixel(p, x, y);
}

int64_t pixels(const Problem& p) { return static_cast<int64_t>(p.cam.width) * p.cam.height; }

void init_cuda(const Problem& p) {
  init_kernel<<<blocks_for(pixels(p)), kThreads, 0, at::cuda::getCurrentCUDAStream()>>>(p);
  C10_CUDA_KERNEL_LAUNCH_CHECK();
}

void update_cuda(const Problem& p, int colour, int iteration) {
  const int64_t slots = static_cast<int64_t>((p.cam.width + 1) / 2) * p.cam.height;
  update_kernel<<<blocks_for(slots), kThreads, 0, at::cuda::getCurrentCUDAStream()>>>(p, colour, iteration);
  C10_CUDA_KERNEL_LAUNCH_CHECK();
}

void rescore_cuda(const Problem& p) {
  rescore_kernel<<<blocks_for(pixels(p)), kThreads, 0, at::cuda::getCurrentCUDAStream()>>>(p);
  C10_CUDA_KERNEL_LAUNCH_CHECK();
}

void filter_cuda(const Problem& p) {
  filter_kernel<<<blocks_for(pixels(p)), kThreads, 0, at::cuda::getCurrentCUDAStream()>>>(p);
  C10_CUDA_KERNEL_LAUNCH_CHECK();
}

}  // namespace

const Backend kCudaBackend{init_cuda, update_cuda, rescore_cuda, filter_cuda};

}  // namespace gaps::pm

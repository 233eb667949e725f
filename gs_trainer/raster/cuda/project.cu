// Projection of 3D Gaussians to 2D conics on the GPU, forward and backward: one thread per Gaussian
// running the shared maths of raster_math.h (project_one, finish_projection, project_one_vjp), so the
// results are those of cpu/project.cpp. The .cu files are compiled without FMA contraction, which keeps
// every float operation rounding as on the CPU (bitwise-equal conics and depths keep the tile sort order
// and the alpha decisions of the rasterizer identical).
#include <algorithm>
#include <vector>

#include <ATen/core/Tensor.h>
#include <ATen/cuda/CUDAContext.h>
#include <ATen/ops/empty.h>
#include <ATen/ops/empty_like.h>
#include <c10/cuda/CUDAGuard.h>

#include "gs_trainer/raster/cuda/cuda_common.h"
#include "gs_trainer/raster/rasterize_backend.h"

namespace gaps::backend {
namespace {

using raster::Intrinsics;
using raster::Mat3;

// The world-to-camera rotation and translation, read on the device so that no host copy of the (CUDA)
// view matrix is needed.
struct View {
  Mat3<float> W;
  float t[3];
};

__device__ View load_view(const float* viewmat) {
  View v;
  for (int r = 0; r < 3; ++r) {
    for (int c = 0; c < 3; ++c) v.W(r, c) = viewmat[4 * r + c];
    v.t[r] = viewmat[4 * r + 3];
  }
  return v;
}

// Up to Capacity cameras' intrinsics, passed by value to the kernel: 32 for a batch of views, 1 for the training
// step, whose launches then carry no more parameters than with a single Intrinsics.
template <int Capacity>
struct ViewIntrinsics {
  Intrinsics K[Capacity];
};

// Grid rows are views (one row for a single view): view y reads viewmat y and intrinsics y and writes output rows
// y·n + i.
template <int Capacity>
__global__ void project_forward_kernel(int64_t n, const float* __restrict__ means, const float* __restrict__ quats,
                                       const float* __restrict__ scales, const float* __restrict__ viewmats,
                                       ViewIntrinsics<Capacity> intrinsics, float* __restrict__ means2d_out,
                                       float* __restrict__ conics_out, float* __restrict__ depths_out,
                                       int32_t* __restrict__ radii_out) {
  const int64_t i = static_cast<int64_t>(blockIdx.x) * blockDim.x + threadIdx.x;
  if (i >= n) return;
  const int64_t row = blockIdx.y * n + i;
  float* means2d = means2d_out + 2 * blockIdx.y * n;
  float* conics = conics_out + 3 * blockIdx.y * n;
  const View v = load_view(viewmats + 16 * blockIdx.y);
  const Intrinsics& K = intrinsics.K[blockIdx.y];
  raster::ProjectionCache<float> cache;
  raster::Projected<float> p{};
  p.visible = false;
  if (raster::project_one(means + 3 * i, quats + 4 * i, scales + 3 * i, v.W, v.t, K, cache))
    p = raster::finish_projection(cache, K);
  // Culled Gaussians get zeros everywhere, as on the CPU.
  radii_out[row] = p.visible ? p.radius : 0;
  means2d[2 * i] = p.visible ? p.mean2d.x : 0.f;
  means2d[2 * i + 1] = p.visible ? p.mean2d.y : 0.f;
  conics[3 * i] = p.visible ? p.conic.a : 0.f;
  conics[3 * i + 1] = p.visible ? p.conic.b : 0.f;
  conics[3 * i + 2] = p.visible ? p.conic.c : 0.f;
  depths_out[row] = p.visible ? p.depth : 0.f;
}

__global__ void project_backward_kernel(int64_t n, const float* __restrict__ means, const float* __restrict__ quats,
                                        const float* __restrict__ scales, const float* __restrict__ viewmat,
                                        Intrinsics K, const int32_t* __restrict__ radii,
                                        const float* __restrict__ g_means2d, const float* __restrict__ g_conics,
                                        float* __restrict__ g_means, float* __restrict__ g_quats,
                                        float* __restrict__ g_scales) {
  const int64_t i = static_cast<int64_t>(blockIdx.x) * blockDim.x + threadIdx.x;
  if (i >= n) return;
  float gm[3] = {0.f, 0.f, 0.f}, gq[4] = {0.f, 0.f, 0.f, 0.f}, gs[3] = {0.f, 0.f, 0.f};
  if (radii[i] > 0) {
    // The forward state is recomputed rather than stored (as on the CPU): a few dozen flops per Gaussian.
    const View v = load_view(viewmat);
    raster::ProjectionCache<float> cache;
    raster::project_one(means + 3 * i, quats + 4 * i, scales + 3 * i, v.W, v.t, K, cache);
    const raster::Vec2<float> g2{g_means2d[2 * i], g_means2d[2 * i + 1]};
    const raster::Sym2<float> gc{g_conics[3 * i], g_conics[3 * i + 1], g_conics[3 * i + 2]};
    raster::project_one_vjp(cache, v.W, K, g2, gc, gm, gq, gs);
  }
  for (int k = 0; k < 3; ++k) g_means[3 * i + k] = gm[k];
  for (int k = 0; k < 4; ++k) g_quats[4 * i + k] = gq[k];
  for (int k = 0; k < 3; ++k) g_scales[3 * i + k] = gs[k];
}

constexpr int kThreads = kElementwiseThreads;

}  // namespace

namespace {

// Projections of `views` views (viewmats views x 4 x 4, K[0 .. views)), Capacity at a time.
template <int Capacity>
Projection project_views(const at::Tensor& means_in, const at::Tensor& quats_in, const at::Tensor& scales_in,
                         const at::Tensor& viewmats_in, const raster::Intrinsics* K, int64_t views) {
  check_cuda_float("means", means_in);
  check_cuda_float("quats", quats_in);
  check_cuda_float("scales", scales_in);
  check_cuda_float("viewmat", viewmats_in);
  const c10::cuda::CUDAGuard guard(means_in.device());
  const auto means = means_in.contiguous(), quats = quats_in.contiguous(), scales = scales_in.contiguous();
  const auto viewmat = viewmats_in.contiguous();
  const int64_t n = means.size(0), rows = n * views;
  Projection out;
  out.means2d = at::empty({rows, 2}, means.options());
  out.conics = at::empty({rows, 3}, means.options());
  out.depths = at::empty({rows}, means.options());
  out.radii = at::empty({rows}, means.options().dtype(at::kInt));
  if (rows == 0) return out;
  for (int64_t first = 0; first < views; first += Capacity) {
    const int count = static_cast<int>(std::min<int64_t>(Capacity, views - first));
    ViewIntrinsics<Capacity> intrinsics{};
    for (int v = 0; v < count; ++v) intrinsics.K[v] = K[first + v];
    const int64_t row = first * n;
    project_forward_kernel<Capacity><<<dim3(blocks_for(n), count), kThreads, 0, at::cuda::getCurrentCUDAStream()>>>(
        n, means.data_ptr<float>(), quats.data_ptr<float>(), scales.data_ptr<float>(),
        viewmat.data_ptr<float>() + 16 * first, intrinsics, out.means2d.data_ptr<float>() + 2 * row,
        out.conics.data_ptr<float>() + 3 * row, out.depths.data_ptr<float>() + row,
        out.radii.data_ptr<int32_t>() + row);
    C10_CUDA_KERNEL_LAUNCH_CHECK();
  }
  return out;
}

}  // namespace

Projection project_views_forward_cuda(const at::Tensor& means, const at::Tensor& quats, const at::Tensor& scales,
                                      const at::Tensor& viewmats, const std::vector<raster::Intrinsics>& K) {
  TORCH_CHECK(viewmats.dim() == 3 && viewmats.size(0) == static_cast<int64_t>(K.size()),
              "project_views_forward_cuda: ", viewmats.sizes(), " view matrices for ", K.size(), " intrinsics");
  return project_views<kMaxViews>(means, quats, scales, viewmats, K.data(), viewmats.size(0));
}

Projection project_forward_cuda(const at::Tensor& means, const at::Tensor& quats, const at::Tensor& scales,
                                const at::Tensor& viewmat, const raster::Intrinsics& K) {
  return project_views<1>(means, quats, scales, viewmat, &K, 1);
}

ProjectionGrads project_backward_cuda(const at::Tensor& means_in, const at::Tensor& quats_in,
                                      const at::Tensor& scales_in, const at::Tensor& viewmat_in,
                                      const raster::Intrinsics& K, const at::Tensor& radii_in,
                                      const at::Tensor& g_means2d_in, const at::Tensor& g_conics_in) {
  check_cuda_float("means", means_in);
  check_cuda_float("g_means2d", g_means2d_in);
  check_cuda_float("g_conics", g_conics_in);
  const c10::cuda::CUDAGuard guard(means_in.device());
  const auto means = means_in.contiguous(), quats = quats_in.contiguous(), scales = scales_in.contiguous();
  const auto viewmat = viewmat_in.contiguous(), radii = radii_in.contiguous();
  const auto g_means2d = g_means2d_in.contiguous(), g_conics = g_conics_in.contiguous();
  const int64_t n = means.size(0);
  ProjectionGrads out;
  out.means = at::empty_like(means);
  out.quats = at::empty_like(quats);
  out.scales = at::empty_like(scales);
  if (n == 0) return out;
  project_backward_kernel<<<blocks_for(n), kThreads, 0, at::cuda::getCurrentCUDAStream()>>>(
      n, means.data_ptr<float>(), quats.data_ptr<float>(), scales.data_ptr<float>(), viewmat.data_ptr<float>(), K,
      radii.data_ptr<int32_t>(), g_means2d.data_ptr<float>(), g_conics.data_ptr<float>(), out.means.data_ptr<float>(),
      out.quats.data_ptr<float>(), out.scales.data_ptr<float>());
  C10_CUDA_KERNEL_LAUNCH_CHECK();
  return out;
}

}  // namespace gaps::backend

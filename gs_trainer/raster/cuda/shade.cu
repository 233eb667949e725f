// Per-Gaussian colour (SH at the view direction) and distance on the GPU, forward and backward: one thread
// per Gaussian running shade_math.h, the maths of cpu/shade.cpp. One kernel each way replaces the few dozen
// element-wise ATen launches (and their autograd nodes) that the same computation costs in tensor ops.
#include <algorithm>
#include <vector>

#include <ATen/core/Tensor.h>
#include <ATen/cuda/CUDAContext.h>
#include <ATen/ops/empty.h>
#include <ATen/ops/empty_like.h>
#include <c10/cuda/CUDAGuard.h>

#include "gs_trainer/raster/cuda/cuda_common.h"
#include "gs_trainer/raster/rasterize_backend.h"
#include "gs_trainer/raster/shade_math.h"

namespace gaps::backend {
namespace {

void check_inputs(const at::Tensor& means, const at::Tensor& sh_dc, const at::Tensor& sh_rest) {
  check_cuda_float("means", means);
  check_cuda_float("sh_dc", sh_dc);
  check_cuda_float("sh_rest", sh_rest);
}

struct CentreF {
  float c[3];
};

template <int Degree>
__global__ void shade_forward_kernel(int64_t n, CentreF centre, const float* __restrict__ means,
                                     const float* __restrict__ dc, const float* __restrict__ rest, int64_t stride,
                                     float* __restrict__ out) {
  const int64_t i = static_cast<int64_t>(blockIdx.x) * blockDim.x + threadIdx.x;
  if (i >= n) return;
  float m[3], d[3], o[4];
  for (int k = 0; k < 3; ++k) {
    m[k] = means[3 * i + k];
    d[k] = dc[3 * i + k];
  }
  raster::shade_one(Degree, m, centre.c, d, rest + stride * i, o);
  reinterpret_cast<float4*>(out)[i] = make_float4(o[0], o[1], o[2], o[3]);
}

// The degree is a template argument (as in every kernel of this file): with a runtime degree the basis and its
// gradient were indexed in local memory, which made this the costliest kernel of a training step after the
// compositing passes.
template <int Degree>
__global__ void shade_backward_kernel(int64_t n, CentreF centre, const float* __restrict__ means,
                                      const float* __restrict__ dc, const float* __restrict__ rest, int64_t stride,
                                      const float* __restrict__ g_features, float* __restrict__ g_means,
                                      float* __restrict__ g_dc, float* __restrict__ g_rest) {
  const int64_t i = static_cast<int64_t>(blockIdx.x) * blockDim.x + threadIdx.x;
  if (i >= n) return;
  float m[3], d[3], gm[3], gd[3];
  for (int k = 0; k < 3; ++k) {
    m[k] = means[3 * i + k];
    d[k] = dc[3 * i + k];
  }
  const float gf[4] = {g_features[4 * i], g_features[4 * i + 1], g_features[4 * i + 2], g_features[4 * i + 3]};
  raster::shade_one_vjp(Degree, m, centre.c, d, rest + stride * i, gf, gm, gd, g_rest + stride * i);
  // Coefficients above the active degree get no gradient (written here: no separate clearing pass).
  for (int64_t k = 3 * ((Degree + 1) * (Degree + 1) - 1); k < stride; ++k) g_rest[stride * i + k] = 0.f;
  for (int k = 0; k < 3; ++k) {
    g_means[3 * i + k] = gm[k];
    g_dc[3 * i + k] = gd[k];
  }
}

// Calls f(kernel<degree>) for an SH degree of 0 to 3.
template <template <int> class KernelOf, typename F>
void dispatch_degree(int degree, F&& f) {
  TORCH_CHECK(degree >= 0 && degree <= 3, "the CUDA shading kernels take SH degrees 0 to 3, got ", degree);
  switch (degree) {
    case 0:
      f(KernelOf<0>::kernel);
      break;
    case 1:
      f(KernelOf<1>::kernel);
      break;
    case 2:
      f(KernelOf<2>::kernel);
      break;
    default:
      f(KernelOf<3>::kernel);
      break;
  }
}

// Up to kMaxViews camera centres, passed by value to the kernel.
struct CentresF {
  float c[kMaxViews][3];
};

// One thread per Gaussian shades it for every view: the coefficients are read once into registers instead of once
// per view, which is what a view's shading spends most of its time on. Output row v·n + i for view v; zeros where
// the Gaussian is culled in the view (radius 0), which no tile reads. The degree is a template argument so that the
// coefficient loops unroll and the coefficients stay in registers (a runtime count indexes them in local memory).
template <int Degree>
__global__ void shade_views_forward_kernel(int64_t n, int views, CentresF centres, const float* __restrict__ means,
                                           const float* __restrict__ dc, const float* __restrict__ rest, int64_t stride,
                                           const int* __restrict__ radii, float* __restrict__ out) {
  const int64_t i = static_cast<int64_t>(blockIdx.x) * blockDim.x + threadIdx.x;
  if (i >= n) return;
  constexpr int kUsed = 3 * ((Degree + 1) * (Degree + 1) - 1);
  float m[3], d[3], r[kUsed > 0 ? kUsed : 1];
  for (int k = 0; k < 3; ++k) {
    m[k] = means[3 * i + k];
    d[k] = dc[3 * i + k];
  }
#pragma unroll
  for (int k = 0; k < kUsed; ++k) r[k] = rest[stride * i + k];
  for (int v = 0; v < views; ++v) {
    float o[4] = {0.f, 0.f, 0.f, 0.f};
    if (radii[v * n + i] > 0) raster::shade_one(Degree, m, centres.c[v], d, r, o);
    reinterpret_cast<float4*>(out)[v * n + i] = make_float4(o[0], o[1], o[2], o[3]);
  }
}

template <int Degree>
struct ShadeForward {
  static constexpr auto kernel = shade_forward_kernel<Degree>;
};
template <int Degree>
struct ShadeViewsForward {
  static constexpr auto kernel = shade_views_forward_kernel<Degree>;
};
template <int Degree>
struct ShadeBackward {
  static constexpr auto kernel = shade_backward_kernel<Degree>;
};

constexpr int kThreads = kElementwiseThreads;
CentreF to_float(const Centre& c) { return {{float(c.x), float(c.y), float(c.z)}}; }

}  // namespace

at::Tensor shade_forward_cuda(const at::Tensor& means_in, const at::Tensor& sh_dc_in, const at::Tensor& sh_rest_in,
                              int degree, const Centre& centre) {
  check_inputs(means_in, sh_dc_in, sh_rest_in);
  const c10::cuda::CUDAGuard guard(means_in.device());
  const auto means = means_in.contiguous(), dc = sh_dc_in.contiguous(), rest = sh_rest_in.contiguous();
  const int64_t n = means.size(0);
  at::Tensor out = at::empty({n, 4}, means.options());
  if (n == 0) return out;
  dispatch_degree<ShadeForward>(degree, [&](auto kernel) {
    kernel<<<blocks_for(n), kThreads, 0, at::cuda::getCurrentCUDAStream()>>>(
        n, to_float(centre), means.data_ptr<float>(), dc.data_ptr<float>(), rest.data_ptr<float>(), rest.size(1) * 3,
        out.data_ptr<float>());
  });
  C10_CUDA_KERNEL_LAUNCH_CHECK();
  return out;
}

at::Tensor shade_views_forward_cuda(const at::Tensor& means_in, const at::Tensor& sh_dc_in,
                                    const at::Tensor& sh_rest_in, int degree, const std::vector<Centre>& centres,
                                    const at::Tensor& radii_in) {
  check_inputs(means_in, sh_dc_in, sh_rest_in);
  const c10::cuda::CUDAGuard guard(means_in.device());
  const auto means = means_in.contiguous(), dc = sh_dc_in.contiguous(), rest = sh_rest_in.contiguous();
  const int64_t n = means.size(0), views = static_cast<int64_t>(centres.size());
  TORCH_CHECK(radii_in.is_cuda() && radii_in.scalar_type() == at::kInt && radii_in.numel() == views * n,
              "shade_views_forward_cuda: radii must be ", views, " x ", n, " int32 on the GPU, got ", radii_in.sizes());
  const at::Tensor radii = radii_in.contiguous();
  at::Tensor out = at::empty({views * n, 4}, means.options());
  if (n == 0) return out;
  for (int64_t first = 0; first < views; first += kMaxViews) {
    const int count = static_cast<int>(std::min<int64_t>(kMaxViews, views - first));
    CentresF c{};
    for (int v = 0; v < count; ++v) {
      const CentreF f = to_float(centres[first + v]);
      for (int k = 0; k < 3; ++k) c.c[v][k] = f.c[k];
    }
    const auto launch = [&](auto kernel) {
      kernel<<<blocks_for(n), kThreads, 0, at::cuda::getCurrentCUDAStream()>>>(
          n, count, c, means.data_ptr<float>(), dc.data_ptr<float>(), rest.data_ptr<float>(), rest.size(1) * 3,
          radii.data_ptr<int>() + first * n, out.data_ptr<float>() + 4 * first * n);
    };
    dispatch_degree<ShadeViewsForward>(degree, launch);
    C10_CUDA_KERNEL_LAUNCH_CHECK();
  }
  return out;
}

ShadeGrads shade_backward_cuda(const at::Tensor& means_in, const at::Tensor& sh_dc_in, const at::Tensor& sh_rest_in,
                               int degree, const Centre& centre, const at::Tensor& g_features_in) {
  check_inputs(means_in, sh_dc_in, sh_rest_in);
  check_cuda_float("g_features", g_features_in);
  const c10::cuda::CUDAGuard guard(means_in.device());
  const auto means = means_in.contiguous(), dc = sh_dc_in.contiguous(), rest = sh_rest_in.contiguous();
  const auto g_features = g_features_in.contiguous();
  const int64_t n = means.size(0);
  ShadeGrads g;
  g.means = at::empty_like(means);
  g.sh_dc = at::empty_like(dc);
  g.sh_rest = at::empty_like(rest);
  if (n == 0) return g;
  TORCH_CHECK(g_features.size(0) == n && g_features.size(1) == 4, "shade_backward_cuda: g_features must be ", n,
              " x 4, got ", g_features.sizes());
  dispatch_degree<ShadeBackward>(degree, [&](auto kernel) {
    kernel<<<blocks_for(n), kThreads, 0, at::cuda::getCurrentCUDAStream()>>>(
        n, to_float(centre), means.data_ptr<float>(), dc.data_ptr<float>(), rest.data_ptr<float>(), rest.size(1) * 3,
        g_features.data_ptr<float>(), g.means.data_ptr<float>(), g.sh_dc.data_ptr<float>(),
        g.sh_rest.data_ptr<float>());
  });
  C10_CUDA_KERNEL_LAUNCH_CHECK();
  return g;
}

}  // namespace gaps::backend

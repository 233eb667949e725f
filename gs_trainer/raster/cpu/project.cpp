// Projection of 3D Gaussians to 2D conics (EWA splatting), forward and backward, on the CPU.
#include <ATen/ATen.h>
#include <ATen/Dispatch.h>
#include <ATen/Parallel.h>

#include "gs_trainer/raster/rasterize_backend.h"

namespace gaps::backend {
namespace {

template <typename T>
void split_viewmat(const at::Tensor& viewmat, raster::Mat3<T>& W, T t[3]) {
  auto v = viewmat.to(at::kDouble).contiguous();
  auto a = v.accessor<double, 2>();
  for (int r = 0; r < 3; ++r) {
    for (int c = 0; c < 3; ++c) W(r, c) = T(a[r][c]);
    t[r] = T(a[r][3]);
  }
}

template <typename T>
void project_forward_impl(const at::Tensor& means, const at::Tensor& quats, const at::Tensor& scales,
                          const at::Tensor& viewmat, const raster::Intrinsics& K, Projection& out) {
  raster::Mat3<T> W;
  T tvec[3];
  split_viewmat(viewmat, W, tvec);
  const T* m = means.data_ptr<T>();
  const T* q = quats.data_ptr<T>();
  const T* s = scales.data_ptr<T>();
  T* m2 = out.means2d.data_ptr<T>();
  T* con = out.conics.data_ptr<T>();
  T* dep = out.depths.data_ptr<T>();
  int32_t* rad = out.radii.data_ptr<int32_t>();
  at::parallel_for(0, means.size(0), 4096, [&](int64_t begin, int64_t end) {
    for (int64_t i = begin; i < end; ++i) {
      raster::ProjectionCache<T> cache;
      rad[i] = 0;
      if (!raster::project_one(m + 3 * i, q + 4 * i, s + 3 * i, W, tvec, K, cache)) continue;
      const auto p = raster::finish_projection(cache, K);
      if (!p.visible) continue;
      rad[i] = p.radius;
      m2[2 * i] = p.mean2d.x;
      m2[2 * i + 1] = p.mean2d.y;
      con[3 * i] = p.conic.a;
      con[3 * i + 1] = p.conic.b;
      con[3 * i + 2] = p.conic.c;
      dep[i] = p.depth;
    }
  });
}

template <typename T>
void project_backward_impl(const at::Tensor& means, const at::Tensor& quats, const at::Tensor& scales,
                           const at::Tensor& viewmat, const raster::Intrinsics& K, const at::Tensor& radii,
                           const at::Tensor& g_means2d, const at::Tensor& g_conics, ProjectionGrads& out) {
  raster::Mat3<T> W;
  T tvec[3];
  split_viewmat(viewmat, W, tvec);
  const T* m = means.data_ptr<T>();
  const T* q = quats.data_ptr<T>();
  const T* s = scales.data_ptr<T>();
  const int32_t* rad = radii.data_ptr<int32_t>();
  const T* gm2 = g_means2d.data_ptr<T>();
  const T* gcon = g_conics.data_ptr<T>();
  T* gm = out.means.data_ptr<T>();
  T* gq = out.quats.data_ptr<T>();
  T* gs = out.scales.data_ptr<T>();
  at::parallel_for(0, means.size(0), 4096, [&](int64_t begin, int64_t end) {
    for (int64_t i = begin; i < end; ++i) {
      if (rad[i] <= 0) continue;
      raster::ProjectionCache<T> cache;
      raster::project_one(m + 3 * i, q + 4 * i, s + 3 * i, W, tvec, K, cache);
      const raster::Vec2<T> g2{gm2[2 * i], gm2[2 * i + 1]};
      const raster::Sym2<T> gc{gcon[3 * i], gcon[3 * i + 1], gcon[3 * i + 2]};
      raster::project_one_vjp(cache, W, K, g2, gc, gm + 3 * i, gq + 4 * i, gs + 3 * i);
    }
  });
}

}  // namespace

Projection project_forward_cpu(const at::Tensor& means_in, const at::Tensor& quats_in, const at::Tensor& scales_in,
                               const at::Tensor& viewmat, const raster::Intrinsics& K) {
  const auto means = means_in.contiguous(), quats = quats_in.contiguous(), scales = scales_in.contiguous();
  const int64_t n = means.size(0);
  Projection out;
  out.means2d = at::zeros({n, 2}, means.options());
  out.conics = at::zeros({n, 3}, means.options());
  out.depths = at::zeros({n}, means.options());
  out.radii = at::zeros({n}, means.options().dtype(at::kInt));
  AT_DISPATCH_FLOATING_TYPES(means.scalar_type(), "project_forward_cpu",
                             [&] { project_forward_impl<scalar_t>(means, quats, scales, viewmat, K, out); });
  return out;
}

ProjectionGrads project_backward_cpu(const at::Tensor& means_in, const at::Tensor& quats_in,
                                     const at::Tensor& scales_in, const at::Tensor& viewmat,
                                     const raster::Intrinsics& K, const at::Tensor& radii, const at::Tensor& g_means2d,
                                     const at::Tensor& g_conics) {
  const auto means = means_in.contiguous(), quats = quats_in.contiguous(), scales = scales_in.contiguous();
  ProjectionGrads out;
  out.means = at::zeros_like(means);
  out.quats = at::zeros_like(quats);
  out.scales = at::zeros_like(scales);
  AT_DISPATCH_FLOATING_TYPES(means.scalar_type(), "project_backward_cpu", [&] {
    project_backward_impl<scalar_t>(means, quats, scales, viewmat, K, radii.contiguous(), g_means2d.contiguous(),
                                    g_conics.contiguous(), out);
  });
  return out;
}

Projection project_views_forward_cpu(const at::Tensor& means, const at::Tensor& quats, const at::Tensor& scales,
                                     const at::Tensor& viewmats, const std::vector<raster::Intrinsics>& K) {
  TORCH_CHECK(static_cast<int64_t>(K.size()) == viewmats.size(0), "project_views_forward_cpu: ", viewmats.size(0),
              " view matrices but ", K.size(), " intrinsics");
  std::vector<at::Tensor> means2d, conics, depths, radii;
  for (int64_t v = 0; v < viewmats.size(0); ++v) {
    const Projection p = project_forward_cpu(means, quats, scales, viewmats[v], K[v]);
    means2d.push_back(p.means2d);
    conics.push_back(p.conics);
    depths.push_back(p.depths);
    radii.push_back(p.radii);
  }
  if (means2d.empty())
    return project_forward_cpu(means.narrow(0, 0, 0), quats.narrow(0, 0, 0), scales.narrow(0, 0, 0),
                               at::eye(4, means.options()), {1, 1, 0, 0, 1, 1});
  return {at::cat(means2d), at::cat(conics), at::cat(depths), at::cat(radii)};
}

}  // namespace gaps::backend

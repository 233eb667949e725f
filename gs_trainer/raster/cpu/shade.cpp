// Per-Gaussian colour (SH at the view direction) and distance on the CPU, forward and backward, with the
// shared maths of shade_math.h. Shapes are checked by the autograd wrapper (rasterizer.cpp).
#include <algorithm>

#include <ATen/ATen.h>
#include <ATen/Dispatch.h>
#include <ATen/Parallel.h>

#include "gs_trainer/raster/rasterize_backend.h"
#include "gs_trainer/raster/shade_math.h"

namespace gaps::backend {
namespace {

// Shades every Gaussian into o (N x 4), or, given radii (N), only those with a radius, zeroing the rest.
template <typename T>
void shade_forward_impl(const at::Tensor& means, const at::Tensor& dc, const at::Tensor& rest, int degree,
                        const Centre& centre, const int32_t* radii, T* o) {
  const T c[3] = {T(centre.x), T(centre.y), T(centre.z)};
  const T* m = means.data_ptr<T>();
  const T* d = dc.data_ptr<T>();
  const T* r = rest.data_ptr<T>();
  const int64_t stride = rest.size(1) * 3;
  at::parallel_for(0, means.size(0), 8192, [&](int64_t begin, int64_t end) {
    for (int64_t i = begin; i < end; ++i) {
      if (radii && radii[i] == 0)
        std::fill_n(o + 4 * i, 4, T(0));
      else
        raster::shade_one(degree, m + 3 * i, c, d + 3 * i, r + stride * i, o + 4 * i);
    }
  });
}

template <typename T>
void shade_backward_impl(const at::Tensor& means, const at::Tensor& dc, const at::Tensor& rest, int degree,
                         const Centre& centre, const at::Tensor& g_features, ShadeGrads& g) {
  const T c[3] = {T(centre.x), T(centre.y), T(centre.z)};
  const T* m = means.data_ptr<T>();
  const T* d = dc.data_ptr<T>();
  const T* r = rest.data_ptr<T>();
  const T* gf = g_features.data_ptr<T>();
  const int64_t stride = rest.size(1) * 3;
  T* gm = g.means.data_ptr<T>();
  T* gd = g.sh_dc.data_ptr<T>();
  T* gr = g.sh_rest.data_ptr<T>();
  at::parallel_for(0, means.size(0), 8192, [&](int64_t begin, int64_t end) {
    for (int64_t i = begin; i < end; ++i)
      raster::shade_one_vjp(degree, m + 3 * i, c, d + 3 * i, r + stride * i, gf + 4 * i, gm + 3 * i, gd + 3 * i,
                            gr + stride * i);
  });
}

}  // namespace

at::Tensor shade_forward_cpu(const at::Tensor& means_in, const at::Tensor& sh_dc_in, const at::Tensor& sh_rest_in,
                             int degree, const Centre& centre) {
  const auto means = means_in.contiguous(), dc = sh_dc_in.contiguous(), rest = sh_rest_in.contiguous();
  at::Tensor out = at::empty({means.size(0), 4}, means.options());
  AT_DISPATCH_FLOATING_TYPES(means.scalar_type(), "shade_forward_cpu", [&] {
    shade_forward_impl<scalar_t>(means, dc, rest, degree, centre, nullptr, out.data_ptr<scalar_t>());
  });
  return out;
}

ShadeGrads shade_backward_cpu(const at::Tensor& means_in, const at::Tensor& sh_dc_in, const at::Tensor& sh_rest_in,
                              int degree, const Centre& centre, const at::Tensor& g_features_in) {
  const auto means = means_in.contiguous(), dc = sh_dc_in.contiguous(), rest = sh_rest_in.contiguous();
  const auto g_features = g_features_in.to(means.scalar_type()).contiguous();
  ShadeGrads g;
  g.means = at::empty_like(means);
  g.sh_dc = at::empty_like(dc);
  g.sh_rest = at::zeros_like(rest);  // rows above the active degree get no gradient
  AT_DISPATCH_FLOATING_TYPES(means.scalar_type(), "shade_backward_cpu",
                             [&] { shade_backward_impl<scalar_t>(means, dc, rest, degree, centre, g_features, g); });
  return g;
}

at::Tensor shade_views_forward_cpu(const at::Tensor& means, const at::Tensor& sh_dc, const at::Tensor& sh_rest,
                                   int degree, const std::vector<Centre>& centres, const at::Tensor& radii) {
  TORCH_CHECK(radii.numel() == static_cast<int64_t>(centres.size()) * means.size(0),
              "shade_views_forward_cpu: radii must be ", centres.size(), " x ", means.size(0), ", got ", radii.sizes());
  const auto m = means.contiguous(), dc = sh_dc.contiguous(), rest = sh_rest.contiguous();
  const at::Tensor r = radii.reshape({-1}).to(at::kInt).contiguous();
  const int64_t n = m.size(0);
  at::Tensor out = at::empty({static_cast<int64_t>(centres.size()) * n, 4}, m.options());
  AT_DISPATCH_FLOATING_TYPES(m.scalar_type(), "shade_views_forward_cpu", [&] {
    for (size_t v = 0; v < centres.size(); ++v)  // a Gaussian a view culls is not shaded for it
      shade_forward_impl<scalar_t>(m, dc, rest, degree, centres[v], r.data_ptr<int32_t>() + v * n,
                                   out.data_ptr<scalar_t>() + 4 * v * n);
  });
  return out;
}

}  // namespace gaps::backend

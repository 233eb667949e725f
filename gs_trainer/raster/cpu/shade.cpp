// Per-Gaussian colour (SH at the view direction) and distance on the CPU, forward and backward, with the
// shared maths of shade_math.h. Shapes are checked by the autograd wrapper (rasterizer.cpp).
#include <ATen/ATen.h>
#include <ATen/Dispatch.h>
#include <ATen/Parallel.h>

#include "gs_trainer/raster/rasterize_backend.h"
#include "gs_trainer/raster/shade_math.h"

namespace gaps::backend {
namespace {

template <typename T>
void shade_forward_impl(const at::Tensor& means, const at::Tensor& dc, const at::Tensor& rest, int degree,
                        const Centre& centre, at::Tensor& out) {
  const T c[3] = {T(centre.x), T(centre.y), T(centre.z)};
  const T* m = means.data_ptr<T>();
  const T* d = dc.data_ptr<T>();
  const T* r = rest.data_ptr<T>();
  const int64_t stride = rest.size(1) * 3;
  T* o = out.data_ptr<T>();
  at::parallel_for(0, means.size(0), 8192, [&](int64_t begin, int64_t end) {
    for (int64_t i = begin; i < end; ++i) raster::shade_one(degree, m + 3 * i, c, d + 3 * i, r + stride * i, o + 4 * i);
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
  AT_DISPATCH_FLOATING_TYPES(means.scalar_type(), "shade_forward_cpu",
                             [&] { shade_forward_impl<scalar_t>(means, dc, rest, degree, centre, out); });
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
  std::vector<at::Tensor> features;
  for (const Centre& c : centres) features.push_back(shade_forward_cpu(means, sh_dc, sh_rest, degree, c));
  if (features.empty()) return at::empty({0, 4}, means.options());
  return at::cat(features).masked_fill_(radii.reshape({-1, 1}) == 0, 0);
}

}  // namespace gaps::backend

// The SSIM map and its backward pass on the CPU (ssim_math.h), rows in parallel, and the training loss over them.
#include <ATen/ATen.h>
#include <ATen/Dispatch.h>
#include <ATen/Parallel.h>

#include "gs_trainer/raster/ssim_backend.h"
#include "gs_trainer/raster/ssim_math.h"

namespace gaps::backend {
namespace {

ssim::Shape shape_of(const at::Tensor& image) {
  return {static_cast<int>(image.size(0)), static_cast<int>(image.size(1)), static_cast<int>(image.size(2))};
}

// Calls f(y, x, c) for every element, rows split across threads.
template <typename F>
void for_each_element(const ssim::Shape& s, const F& f) {
  at::parallel_for(0, s.height, 8, [&](int64_t begin, int64_t end) {
    for (int64_t y = begin; y < end; ++y)
      for (int x = 0; x < s.width; ++x)
        for (int c = 0; c < s.channels; ++c) f(static_cast<int>(y), x, c);
  });
}

template <typename T>
void forward_impl(const at::Tensor& pred, const at::Tensor& gt, SsimForward& out) {
  const ssim::Shape s = shape_of(pred);
  const auto win = ssim::gaussian_window<T>();
  at::Tensor rows = at::empty({s.height, s.width, s.channels, ssim::kMoments}, pred.options());
  const T* p = pred.data_ptr<T>();
  const T* g = gt.data_ptr<T>();
  T* r = rows.data_ptr<T>();
  for_each_element(s, [&](int y, int x, int c) {
    ssim::horizontal_moments(p, g, s, win, y, x, c, r + ((int64_t(y) * s.width + x) * s.channels + c) * ssim::kMoments);
  });
  T* map = out.map.data_ptr<T>();
  T* partials = out.partials.data_ptr<T>();
  for_each_element(s, [&](int y, int x, int c) {
    const int64_t i = (int64_t(y) * s.width + x) * s.channels + c;
    T m[ssim::kMoments];
    ssim::vertical_pass<T, ssim::kMoments>(r, s, win, y, x, c, m);
    map[i] = ssim::ssim_value_and_partials(m, partials + i * ssim::kPartials);
  });
}

template <typename T>
void backward_impl(const at::Tensor& pred, const at::Tensor& gt, const at::Tensor& partials, const at::Tensor& g_map,
                   at::Tensor& g_pred) {
  const ssim::Shape s = shape_of(pred);
  const auto win = ssim::gaussian_window<T>();
  at::Tensor rows = at::empty({s.height, s.width, s.channels, ssim::kPartials}, pred.options());
  const T* part = partials.data_ptr<T>();
  const T* gm = g_map.data_ptr<T>();
  T* r = rows.data_ptr<T>();
  for_each_element(s, [&](int y, int x, int c) {
    ssim::horizontal_gradient(part, ssim::MapGradientArray<T>{gm}, s, win, y, x, c,
                              r + ((int64_t(y) * s.width + x) * s.channels + c) * ssim::kPartials);
  });
  const T* p = pred.data_ptr<T>();
  const T* g = gt.data_ptr<T>();
  T* out = g_pred.data_ptr<T>();
  for_each_element(s, [&](int y, int x, int c) {
    const int64_t i = (int64_t(y) * s.width + x) * s.channels + c;
    T b[ssim::kPartials];
    ssim::vertical_pass<T, ssim::kPartials>(r, s, win, y, x, c, b);
    out[i] = ssim::prediction_gradient(b, p[i], g[i]);
  });
}

}  // namespace

SsimForward ssim_forward_cpu(const at::Tensor& pred_in, const at::Tensor& gt_in) {
  const auto pred = pred_in.contiguous(), gt = gt_in.contiguous();
  SsimForward out;
  out.map = at::empty_like(pred);
  out.partials = at::empty({pred.size(0), pred.size(1), pred.size(2), ssim::kPartials}, pred.options());
  AT_DISPATCH_FLOATING_TYPES(pred.scalar_type(), "ssim_forward_cpu", [&] { forward_impl<scalar_t>(pred, gt, out); });
  return out;
}

at::Tensor ssim_backward_cpu(const at::Tensor& pred_in, const at::Tensor& gt_in, const at::Tensor& partials_in,
                             const at::Tensor& g_map_in) {
  const auto pred = pred_in.contiguous(), gt = gt_in.contiguous(), partials = partials_in.contiguous();
  const auto g_map = g_map_in.to(pred.scalar_type()).contiguous();
  at::Tensor g_pred = at::empty_like(pred);
  AT_DISPATCH_FLOATING_TYPES(pred.scalar_type(), "ssim_backward_cpu",
                             [&] { backward_impl<scalar_t>(pred, gt, partials, g_map, g_pred); });
  return g_pred;
}

PhotometricForward photometric_forward_cpu(const at::Tensor& pred, const at::Tensor& gt, const at::Tensor& weight,
                                           double lambda) {
  const SsimForward f = ssim_forward_cpu(pred, gt);
  const at::Tensor diff = pred - gt;
  at::Tensor loss;
  if (weight.defined()) {
    loss = (1.0 - lambda) * (weight * diff.abs()).mean() + lambda * (weight * (1.0 - f.map)).mean();
  } else {
    loss = (1.0 - lambda) * diff.abs().mean() + lambda * (1.0 - f.map.mean());
  }
  return {loss, f.partials};
}

at::Tensor photometric_backward_cpu(const at::Tensor& pred, const at::Tensor& gt, const at::Tensor& partials,
                                    const at::Tensor& weight, double lambda, const at::Tensor& g_loss) {
  const int64_t n = pred.numel();
  // As autograd: the scalar factors, then the mean's division, then the weight, then |.|'s sign.
  at::Tensor g_l1 = ((g_loss * (1.0 - lambda)) / n).expand(pred.sizes());
  at::Tensor g_map = ((g_loss * lambda) / n).expand(pred.sizes());
  if (weight.defined()) {
    g_l1 = g_l1 * weight;
    g_map = g_map * weight;
  }
  g_map = g_map.neg().contiguous();
  const at::Tensor g_ssim = ssim_backward_cpu(pred, gt, partials, g_map);
  return g_ssim + g_l1 * (pred - gt).sgn();
}

}  // namespace gaps::backend

#include "gs_trainer/model/render.h"

#include <algorithm>
#include <array>
#include <cstdint>
#include <deque>
#include <optional>
#include <stdexcept>

#include <ATen/ATen.h>
#include <ATen/core/grad_mode.h>
#include <torch/csrc/autograd/custom_function.h>

#include "gs_trainer/model/cuda/activations_cuda.h"
#include "gs_trainer/raster/rasterizer.h"

namespace gaps {
namespace {

// Small per-view constants go to the GPU without waiting for queued work (a pageable copy would).
at::Tensor upload(const at::Tensor& host, const at::TensorOptions& opts) {
  if (!opts.device().is_cuda() || host.is_cuda()) return host.to(opts);
  return host.to(opts.dtype()).pin_memory().to(opts.device(), /*non_blocking=*/true);
}

// The camera's view matrix on the model's device. Training renders the same few cameras thousands of times and
// an upload per step (a host tensor, a pinned staging buffer, a copy) cost more host time than the projection's
// kernel, so each thread keeps the matrices it uploaded last, keyed by the pose itself.
at::Tensor device_viewmat(const Camera& camera, const at::TensorOptions& opts) {
  if (!opts.device().is_cuda()) return camera.viewmat().to(opts);
  struct Entry {
    std::array<double, 12> pose;
    c10::Device device;
    at::ScalarType dtype;
    at::Tensor viewmat;
  };
  constexpr size_t kCapacity = 64;
  thread_local std::deque<Entry> cache;
  std::array<double, 12> pose;
  for (int r = 0; r < 3; ++r) {
    for (int c = 0; c < 3; ++c) pose[4 * r + c] = camera.R(r, c);
    pose[4 * r + 3] = camera.t(r);
  }
  const auto dtype = c10::typeMetaToScalarType(opts.dtype());
  for (const Entry& e : cache)
    if (e.pose == pose && e.device == opts.device() && e.dtype == dtype) return e.viewmat;
  if (cache.size() == kCapacity) cache.pop_front();
  cache.push_back({pose, opts.device(), dtype, upload(camera.viewmat(), opts)});
  return cache.back().viewmat;
}

using torch::autograd::AutogradContext;
using torch::autograd::tensor_list;
using torch::autograd::Variable;

// scales = exp(log_scales) and opacities = sigmoid(logits) [* scale], the model's activations, as one autograd node
// instead of two or three. On the CPU (and for double precision) the forward and backward are the ATen operations
// autograd's own nodes use (ExpBackward's grad * result, MulBackward's grad * other, sigmoid_backward), so CPU
// gradients keep their bits; a CUDA float32 model takes one kernel each way (model/cuda/activations.cu).
class ActivationsFunction : public torch::autograd::Function<ActivationsFunction> {
 public:
  static tensor_list forward(AutogradContext* ctx, Variable log_scales, Variable logits,
                             std::optional<at::Tensor> opacity_scale) {
    if (opacity_scale) ctx->saved_data["opacity_scale"] = *opacity_scale;
#if defined(GAPS_CUDA_KERNELS)
    if (fused(log_scales)) {
      const backend::Activations a =
          backend::activations_forward_cuda(log_scales, logits, opacity_scale.value_or(at::Tensor()));
      ctx->save_for_backward({a.scales, a.sigmoid});
      return {a.scales, a.opacities};
    }
#endif
    const at::Tensor scales = at::exp(log_scales), sigmoid = at::sigmoid(logits);
    ctx->save_for_backward({scales, sigmoid});
    return {scales, opacity_scale ? sigmoid * *opacity_scale : sigmoid};
  }

  static tensor_list backward(AutogradContext* ctx, tensor_list grads) {
    const auto s = ctx->get_saved_variables();
    const at::Tensor opacity_scale =
        ctx->saved_data.count("opacity_scale") ? ctx->saved_data["opacity_scale"].toTensor() : at::Tensor();
#if defined(GAPS_CUDA_KERNELS)
    if (fused(s[0])) {
      const backend::ActivationGrads g =
          backend::activations_backward_cuda(grads[0], grads[1], s[0], s[1], opacity_scale);
      return {g.log_scales, g.logits, Variable()};
    }
#endif
    const at::Tensor g_log_scales = grads[0].defined() ? grads[0] * s[0] : at::Tensor();
    at::Tensor g_logits;
    if (grads[1].defined())
      g_logits = at::sigmoid_backward(opacity_scale.defined() ? grads[1] * opacity_scale : grads[1], s[1]);
    return {g_log_scales, g_logits, Variable()};
  }

 private:
  static bool fused(const at::Tensor& t) { return t.is_cuda() && t.scalar_type() == at::kFloat; }
};

}  // namespace

RenderOutput render(const GaussianModel& model, const Camera& camera, const RenderOptions& options) {
  const auto opts = model.means.options();
  const raster::Intrinsics K{camera.fx, camera.fy, camera.cx, camera.cy, camera.width, camera.height};
  std::optional<at::Tensor> opacity_scale;
  if (options.opacity_scale.defined()) opacity_scale = options.opacity_scale;
  const auto activated = ActivationsFunction::apply(model.log_scales, model.opacity_logits, opacity_scale);
  const at::Tensor &scales = activated[0], &opacities = activated[1];
  auto proj = project_gaussians(model.means, model.quats, scales, device_viewmat(camera, opts), K);

  const Eigen::Vector3d c = camera.center();
  const at::Tensor colour_and_distance =
      shade_gaussians(model.means, model.sh_dc, model.sh_rest, model.sh_degree, {c.x(), c.y(), c.z()});

  const auto raster = rasterize_gaussians(proj.means2d, proj.conics, opacities, colour_and_distance, proj.depths,
                                          proj.radii, camera.width, camera.height, options.means2d_abs_sink);
  RenderOutput out;
  out.rgb = options.background.defined()
                ? composite_over_background(raster.features, raster.alpha, upload(options.background, opts))
                : raster.features.narrow(2, 0, 3);
  out.depth = raster.features.select(2, 3);
  out.alpha = raster.alpha;
  out.means2d = proj.means2d;
  out.radii = proj.radii;
  return out;
}

namespace {

raster::Intrinsics intrinsics_of(const Camera& c) { return {c.fx, c.fy, c.cx, c.cy, c.width, c.height}; }

// render_same_size_views of cameras [begin, end) with the model's activations given (no autograd graph).
RenderedViews render_same_size_range(const GaussianModel& model, const at::Tensor& scales, const at::Tensor& opacities,
                                     const std::vector<Camera>& cameras, size_t begin, size_t end) {
  if (begin >= end) throw std::invalid_argument("render_same_size_views: no cameras");
  std::vector<at::Tensor> viewmats;
  std::vector<std::array<double, 3>> centres;
  std::vector<raster::Intrinsics> intrinsics;
  for (size_t k = begin; k < end; ++k) {
    const Camera& camera = cameras[k];
    if (camera.width != cameras[begin].width || camera.height != cameras[begin].height)
      throw std::invalid_argument("render_same_size_views: the cameras differ in image size");
    intrinsics.push_back(intrinsics_of(camera));
    viewmats.push_back(camera.viewmat());
    const Eigen::Vector3d c = camera.center();
    centres.push_back({c.x(), c.y(), c.z()});
  }
  const RasterizedImage images =
      render_views_forward(model.means, model.quats, scales, opacities, model.sh_dc, model.sh_rest, model.sh_degree,
                           upload(at::stack(viewmats), model.means.options()), centres, intrinsics);
  return {images.features.narrow(3, 0, 3), images.features.select(3, 3), images.alpha};
}

}  // namespace

RenderedViews render_same_size_views(const GaussianModel& model, const std::vector<Camera>& cameras) {
  const at::NoGradGuard no_grad;
  return render_same_size_range(model, model.scales(), model.opacities(), cameras, 0, cameras.size());
}

void render_same_size_batches(const GaussianModel& model, const std::vector<Camera>& cameras,
                              const std::function<size_t(const Camera&)>& max_batch,
                              const std::function<void(size_t begin, size_t end, const RenderedViews&)>& use) {
  const at::NoGradGuard no_grad;
  const at::Tensor scales = model.scales(), opacities = model.opacities();
  for (size_t begin = 0, end = 0; begin < cameras.size(); begin = end) {
    const size_t limit = std::min(cameras.size(), begin + std::max<size_t>(max_batch(cameras[begin]), 1));
    end = begin + 1;
    while (end < limit && cameras[end].width == cameras[begin].width && cameras[end].height == cameras[begin].height)
      ++end;
    use(begin, end, render_same_size_range(model, scales, opacities, cameras, begin, end));
  }
}

std::vector<RenderOutput> render_views(const GaussianModel& model, const std::vector<Camera>& cameras) {
  std::vector<RenderOutput> out(cameras.size());
  render_same_size_batches(
      model, cameras, [](const Camera&) { return SIZE_MAX; },
      [&out](size_t begin, size_t end, const RenderedViews& views) {
        for (size_t k = begin; k < end; ++k) {
          const auto v = static_cast<int64_t>(k - begin);
          out[k].rgb = views.rgb[v];
          out[k].depth = views.depth[v];
          out[k].alpha = views.alpha[v];
        }
      });
  return out;
}

at::Tensor blending_weights(const GaussianModel& model, const Camera& camera) {
  const auto opts = model.means.options();
  const raster::Intrinsics K{camera.fx, camera.fy, camera.cx, camera.cy, camera.width, camera.height};
  at::AutoGradMode grad_mode(true);
  const auto proj = project_gaussians(model.means.detach(), model.quats.detach(), model.scales().detach(),
                                      device_viewmat(camera, opts), K);
  at::Tensor probe = at::zeros({model.size(), 1}, opts).requires_grad_(true);
  const auto raster = rasterize_gaussians(proj.means2d, proj.conics, model.opacities().detach(), probe, proj.depths,
                                          proj.radii, camera.width, camera.height);
  raster.features.sum().backward();
  return probe.grad().view({model.size()});
}

}  // namespace gaps

#include "gs_trainer/model/render.h"

#include <ATen/ATen.h>
#include <ATen/core/grad_mode.h>

#include "gs_trainer/raster/rasterizer.h"

namespace gaps {
namespace {

// Small per-view constants go to the GPU without waiting for queued work (a pageable copy would).
at::Tensor upload(const at::Tensor& host, const at::TensorOptions& opts) {
  if (!opts.device().is_cuda() || host.is_cuda()) return host.to(opts);
  return host.to(opts.dtype()).pin_memory().to(opts.device(), /*non_blocking=*/true);
}

}  // namespace

RenderOutput render(const GaussianModel& model, const Camera& camera, const RenderOptions& options) {
  const auto opts = model.means.options();
  const raster::Intrinsics K{camera.fx, camera.fy, camera.cx, camera.cy, camera.width, camera.height};
  auto proj = project_gaussians(model.means, model.quats, model.scales(), upload(camera.viewmat(), opts), K);

  const Eigen::Vector3d c = camera.center();
  const at::Tensor colour_and_distance =
      shade_gaussians(model.means, model.sh_dc, model.sh_rest, model.sh_degree, {c.x(), c.y(), c.z()});

  at::Tensor opacities = model.opacities();
  if (options.opacity_scale.defined()) opacities = opacities * options.opacity_scale;
  const auto raster = rasterize_gaussians(proj.means2d, proj.conics, opacities, colour_and_distance, proj.depths,
                                          proj.radii, camera.width, camera.height, options.means2d_abs_sink);
  RenderOutput out;
  out.rgb = raster.features.narrow(2, 0, 3);
  if (options.background.defined())
    out.rgb = out.rgb + (1 - raster.alpha).unsqueeze(2) * upload(options.background, opts).view({1, 1, 3});
  out.depth = raster.features.select(2, 3);
  out.alpha = raster.alpha;
  out.means2d = proj.means2d;
  out.radii = proj.radii;
  return out;
}

at::Tensor blending_weights(const GaussianModel& model, const Camera& camera) {
  const auto opts = model.means.options();
  const raster::Intrinsics K{camera.fx, camera.fy, camera.cx, camera.cy, camera.width, camera.height};
  at::AutoGradMode grad_mode(true);
  const auto proj = project_gaussians(model.means.detach(), model.quats.detach(), model.scales().detach(),
                                      upload(camera.viewmat(), opts), K);
  at::Tensor probe = at::zeros({model.size(), 1}, opts).requires_grad_(true);
  const auto raster = rasterize_gaussians(proj.means2d, proj.conics, model.opacities().detach(), probe, proj.depths,
                                          proj.radii, camera.width, camera.height);
  raster.features.sum().backward();
  return probe.grad().view({model.size()});
}

}  // namespace gaps

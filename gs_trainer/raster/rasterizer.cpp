// Autograd wrappers: call the backend of the input's device, save what the backward pass needs.
#include "gs_trainer/raster/rasterizer.h"

#include <optional>

#include <ATen/ATen.h>
#include <torch/csrc/autograd/custom_function.h>

#include "gs_trainer/raster/backend.h"

namespace gaps {
namespace {

using torch::autograd::AutogradContext;
using torch::autograd::tensor_list;
using torch::autograd::Variable;

raster::Intrinsics intrinsics_from(AutogradContext* ctx) {
  const auto v = ctx->saved_data["K"].toDoubleVector();
  return {v[0], v[1], v[2], v[3], static_cast<int>(v[4]), static_cast<int>(v[5])};
}

backend::Centre centre_from(AutogradContext* ctx) {
  const auto v = ctx->saved_data["centre"].toDoubleVector();
  return {v[0], v[1], v[2]};
}

class ShadeFunction : public torch::autograd::Function<ShadeFunction> {
 public:
  static tensor_list forward(AutogradContext* ctx, Variable means, Variable sh_dc, Variable sh_rest, int64_t degree,
                             std::vector<double> centre) {
    const backend::Centre c{centre[0], centre[1], centre[2]};
    const at::Tensor features =
        backend::raster_backend(means.device()).shade_forward(means, sh_dc, sh_rest, static_cast<int>(degree), c);
    ctx->save_for_backward({means, sh_dc, sh_rest});
    ctx->saved_data["centre"] = centre;
    ctx->saved_data["degree"] = degree;
    return {features};
  }

  static tensor_list backward(AutogradContext* ctx, tensor_list grads) {
    const auto s = ctx->get_saved_variables();
    const int degree = static_cast<int>(ctx->saved_data["degree"].toInt());
    const at::Tensor g = grads[0].defined() ? grads[0] : at::zeros({s[0].size(0), 4}, s[0].options());
    const backend::ShadeGrads out =
        backend::raster_backend(s[0].device()).shade_backward(s[0], s[1], s[2], degree, centre_from(ctx), g);
    return {out.means, out.sh_dc, out.sh_rest, Variable(), Variable()};
  }
};

class ProjectFunction : public torch::autograd::Function<ProjectFunction> {
 public:
  static tensor_list forward(AutogradContext* ctx, Variable means, Variable quats, Variable scales, Variable viewmat,
                             std::vector<double> K) {
    const raster::Intrinsics intr{K[0], K[1], K[2], K[3], static_cast<int>(K[4]), static_cast<int>(K[5])};
    const backend::Projection p =
        backend::raster_backend(means.device()).project_forward(means, quats, scales, viewmat, intr);
    ctx->save_for_backward({means, quats, scales, viewmat, p.radii});
    ctx->saved_data["K"] = K;
    ctx->mark_non_differentiable({p.depths, p.radii});
    return {p.means2d, p.conics, p.depths, p.radii};
  }

  static tensor_list backward(AutogradContext* ctx, tensor_list grads) {
    const auto s = ctx->get_saved_variables();
    const auto intr = intrinsics_from(ctx);
    const at::Tensor g_means2d = grads[0].defined() ? grads[0] : at::zeros_like(s[0].narrow(1, 0, 2));
    const at::Tensor g_conics = grads[1].defined() ? grads[1] : at::zeros_like(s[2]);
    const backend::ProjectionGrads g = backend::raster_backend(s[0].device())
                                           .project_backward(s[0], s[1], s[2], s[3], intr, s[4], g_means2d, g_conics);
    return {g.means, g.quats, g.scales, Variable(), Variable()};
  }
};

class RasterizeFunction : public torch::autograd::Function<RasterizeFunction> {
 public:
  static tensor_list forward(AutogradContext* ctx, Variable means2d, Variable conics, Variable opacities,
                             Variable features, Variable depths, Variable radii, int64_t width, int64_t height,
                             std::optional<at::Tensor> abs_sink) {
    const int w = static_cast<int>(width), h = static_cast<int>(height);
    const backend::RasterBackend& stages = backend::raster_backend(means2d.device());
    const backend::TileBins bins = stages.bin_tiles(means2d, conics, opacities, radii, depths, w, h);
    const backend::RasterOutput out = stages.rasterize_forward(bins, means2d, conics, opacities, features, w, h);
    ctx->save_for_backward({means2d, conics, opacities, features, bins.gaussian_ids, bins.tile_ranges, out.final_T,
                            out.n_contrib, out.alpha});
    // The sink is an output buffer, not an input of the graph, so it travels outside the saved variables.
    if (abs_sink) ctx->saved_data["abs_sink"] = *abs_sink;
    return {out.features, out.alpha};
  }

  static tensor_list backward(AutogradContext* ctx, tensor_list grads) {
    const auto s = ctx->get_saved_variables();
    const backend::TileBins bins{s[4], s[5]};
    backend::RasterOutput fwd;
    fwd.final_T = s[6];
    fwd.n_contrib = s[7];
    fwd.alpha = s[8];
    const int h = static_cast<int>(fwd.alpha.size(0)), w = static_cast<int>(fwd.alpha.size(1));
    const at::Tensor g_feat = grads[0].defined() ? grads[0] : at::zeros({h, w, s[3].size(1)}, s[3].options());
    const at::Tensor g_alpha = grads[1].defined() ? grads[1] : at::zeros_like(fwd.alpha);
    const bool has_sink = ctx->saved_data.count("abs_sink") > 0;
    const backend::RasterGrads g =
        backend::raster_backend(s[0].device())
            .rasterize_backward(bins, s[0], s[1], s[2], s[3], fwd, g_feat, g_alpha, has_sink);
    if (has_sink) ctx->saved_data["abs_sink"].toTensor().add_(g.means2d_abs);
    return {g.means2d, g.conics, g.opacities, g.features, Variable(), Variable(), Variable(), Variable(), Variable()};
  }
};

void check_shading_inputs(const at::Tensor& means, const at::Tensor& sh_dc, const at::Tensor& sh_rest, int degree) {
  TORCH_CHECK(degree >= 0 && degree <= 3, "SH degree must be 0..3, got ", degree);
  TORCH_CHECK(means.dim() == 2 && means.size(1) == 3, "means must be N x 3, got ", means.sizes());
  const int64_t n = means.size(0), needed = (degree + 1) * (degree + 1) - 1;
  TORCH_CHECK(sh_dc.sizes() == at::IntArrayRef({n, 1, 3}), "sh_dc must be N x 1 x 3, got ", sh_dc.sizes());
  TORCH_CHECK(sh_rest.dim() == 3 && sh_rest.size(0) == n && sh_rest.size(1) >= needed && sh_rest.size(2) == 3,
              "sh_rest must be N x R x 3 with R >= ", needed, " for SH degree ", degree, ", got ", sh_rest.sizes());
  TORCH_CHECK(sh_dc.scalar_type() == means.scalar_type() && sh_rest.scalar_type() == means.scalar_type(),
              "means and SH coefficients must share a dtype");
}

void check_projection_inputs(const at::Tensor& means, const at::Tensor& quats, const at::Tensor& scales) {
  TORCH_CHECK(means.dim() == 2 && means.size(1) == 3, "means must be N x 3, got ", means.sizes());
  TORCH_CHECK(quats.sizes() == at::IntArrayRef({means.size(0), 4}), "quats must be N x 4, got ", quats.sizes());
  TORCH_CHECK(scales.sizes() == means.sizes(), "scales must be N x 3, got ", scales.sizes());
}

// One autograd node (it was a slice, a subtraction, a product and a sum, each a node with its host-side cost in
// every training step).
class OverBackgroundFunction : public torch::autograd::Function<OverBackgroundFunction> {
 public:
  static tensor_list forward(AutogradContext* ctx, Variable features, Variable alpha, Variable background) {
    ctx->save_for_backward({background});
    ctx->saved_data["channels"] = features.size(2);
    return {backend::raster_backend(features.device()).over_background_forward(features, alpha, background)};
  }

  static tensor_list backward(AutogradContext* ctx, tensor_list grads) {
    const at::Tensor background = ctx->get_saved_variables()[0];
    const backend::BackgroundGrads g =
        backend::raster_backend(background.device())
            .over_background_backward(grads[0], background, ctx->saved_data["channels"].toInt());
    return {g.features, g.alpha, Variable()};
  }
};

}  // namespace

at::Tensor shade_gaussians(const at::Tensor& means, const at::Tensor& sh_dc, const at::Tensor& sh_rest, int degree,
                           const std::array<double, 3>& centre) {
  check_shading_inputs(means, sh_dc, sh_rest, degree);
  return ShadeFunction::apply(means, sh_dc, sh_rest, degree, std::vector<double>(centre.begin(), centre.end()))[0];
}

ProjectedGaussians project_gaussians(const at::Tensor& means, const at::Tensor& quats, const at::Tensor& scales,
                                     const at::Tensor& viewmat, const raster::Intrinsics& K) {
  check_projection_inputs(means, quats, scales);
  TORCH_CHECK(viewmat.sizes() == at::IntArrayRef({4, 4}), "viewmat must be 4 x 4, got ", viewmat.sizes());
  const std::vector<double> k{K.fx, K.fy, K.cx, K.cy, double(K.width), double(K.height)};
  auto out = ProjectFunction::apply(means, quats, scales, viewmat.to(means.options()), k);
  return {out[0], out[1], out[2], out[3]};
}

RasterizedImage rasterize_gaussians(const at::Tensor& means2d, const at::Tensor& conics, const at::Tensor& opacities,
                                    const at::Tensor& features, const at::Tensor& depths, const at::Tensor& radii,
                                    int width, int height, const at::Tensor& means2d_abs_sink) {
  const int64_t n = means2d.size(0);
  TORCH_CHECK(conics.sizes() == at::IntArrayRef({n, 3}), "conics must be N x 3, got ", conics.sizes());
  TORCH_CHECK(opacities.sizes() == at::IntArrayRef({n}), "opacities must be N, got ", opacities.sizes());
  TORCH_CHECK(features.dim() == 2 && features.size(0) == n, "features must be N x C, got ", features.sizes());
  TORCH_CHECK(width > 0 && height > 0, "image size must be positive, got ", width, "x", height);
  std::optional<at::Tensor> sink;
  if (means2d_abs_sink.defined()) sink = means2d_abs_sink;
  auto out = RasterizeFunction::apply(means2d, conics, opacities, features, depths, radii, width, height, sink);
  return {out[0], out[1]};
}

RasterizedImage render_views_forward(const at::Tensor& means_in, const at::Tensor& quats_in,
                                     const at::Tensor& scales_in, const at::Tensor& opacities_in,
                                     const at::Tensor& sh_dc_in, const at::Tensor& sh_rest_in, int degree,
                                     const at::Tensor& viewmats, const std::vector<std::array<double, 3>>& centres,
                                     const std::vector<raster::Intrinsics>& K) {
  check_shading_inputs(means_in, sh_dc_in, sh_rest_in, degree);
  check_projection_inputs(means_in, quats_in, scales_in);
  const int64_t n = means_in.size(0);
  const int views = static_cast<int>(centres.size());
  TORCH_CHECK(viewmats.dim() == 3 && viewmats.size(0) == views && viewmats.size(1) == 4 && viewmats.size(2) == 4,
              "render_views_forward: viewmats must be ", views, " x 4 x 4 (one per centre), got ", viewmats.sizes());
  TORCH_CHECK(opacities_in.sizes() == at::IntArrayRef({n}), "opacities must be N, got ", opacities_in.sizes());
  TORCH_CHECK(static_cast<int>(K.size()) == views, "render_views_forward: ", views, " centres but ", K.size(),
              " intrinsics");
  const int width = views > 0 ? K[0].width : 1, height = views > 0 ? K[0].height : 1;
  for (const raster::Intrinsics& k : K)
    TORCH_CHECK(k.width == width && k.height == height && width > 0 && height > 0,
                "render_views_forward: every view needs the same positive image size, got ", k.width, "x", k.height,
                " beside ", width, "x", height);
  const at::NoGradGuard no_grad;
  const at::Tensor means = means_in.detach(), quats = quats_in.detach(), scales = scales_in.detach();
  const backend::RasterBackend& stages = backend::raster_backend(means.device());
  const backend::Projection p = stages.project_views_forward(means, quats, scales, viewmats.to(means.options()), K);
  std::vector<backend::Centre> c;
  for (const auto& centre : centres) c.push_back({centre[0], centre[1], centre[2]});
  const at::Tensor features =
      stages.shade_views_forward(means, sh_dc_in.detach(), sh_rest_in.detach(), degree, c, p.radii);
  const backend::RasterOutput out = stages.rasterize_views_forward(
      views, p.means2d, p.conics, opacities_in.detach().repeat({views}), p.radii, p.depths, features, width, height);
  return {out.features.view({views, height, width, 4}), out.alpha.view({views, height, width})};
}

at::Tensor composite_over_background(const at::Tensor& features, const at::Tensor& alpha,
                                     const at::Tensor& background) {
  TORCH_CHECK(features.dim() == 3 && features.size(2) >= 3,
              "composite_over_background: H x W x C features (C >= 3) "
              "expected, got ",
              features.sizes());
  TORCH_CHECK(background.numel() == 3 && background.device() == features.device(),
              "composite_over_background: the background must be 3 values on the features' device");
  return OverBackgroundFunction::apply(features, alpha, background)[0];
}

}  // namespace gaps

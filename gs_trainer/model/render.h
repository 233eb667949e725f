#pragma once
// Renders a Gaussian model from a camera: colour, the paper's depth (eq. depth_render: alpha-composited
// distance from the camera centre) and alpha, plus what densification needs.
#include <cstddef>
#include <functional>
#include <vector>

#include <ATen/Tensor.h>

#include "gs_trainer/model/gaussians.h"
#include "gs_trainer/scene/camera.h"

namespace gaps {

struct RenderOptions {
  at::Tensor background;        // 3 values composited behind the Gaussians; undefined = black
  at::Tensor opacity_scale;     // N multiplicative opacity factors (e.g. DropGaussian's mask); undefined = 1
  at::Tensor means2d_abs_sink;  // N x 2, receives absolute 2D-mean gradients in backward (optional)
};

struct RenderOutput {
  at::Tensor rgb;      // H x W x 3
  at::Tensor depth;    // H x W  (not normalised by alpha, as in the paper)
  at::Tensor alpha;    // H x W
  at::Tensor means2d;  // N x 2 projected means; call retain_grad() before backward to read their gradient
  at::Tensor radii;    // N int32 screen-space radii, 0 where not visible
};

RenderOutput render(const GaussianModel& model, const Camera& camera, const RenderOptions& options = {});

// The images render() gives for each camera without options (black background): rgb, depth and alpha, bit for bit,
// without an autograd graph (means2d and radii are left undefined). For scoring many views: consecutive cameras
// of one image size are rendered together (render_views_forward: on CUDA one launch per kernel and one
// host synchronisation for all of them), the view matrices uploaded at once, the activations computed once.
std::vector<RenderOutput> render_views(const GaussianModel& model, const std::vector<Camera>& cameras);

// What render_views gives for cameras that all share one image size, left stacked as the rasterizer returns them
// (rgb and depth are views into one V x H x W x 4 tensor): for measuring a batch of views without splitting and
// restacking it. Fails (std::invalid_argument) without cameras or when their sizes differ.
struct RenderedViews {
  at::Tensor rgb;    // V x H x W x 3
  at::Tensor depth;  // V x H x W
  at::Tensor alpha;  // V x H x W
};
RenderedViews render_same_size_views(const GaussianModel& model, const std::vector<Camera>& cameras);

// Renders the cameras as render_same_size_views does, in batches of consecutive cameras of one image size, at
// most max_batch(first camera of the batch) of them each (>= 1), with the model's activations computed once for
// all batches; hands each batch to use() with the range [begin, end) of cameras it holds, in order.
void render_same_size_batches(const GaussianModel& model, const std::vector<Camera>& cameras,
                              const std::function<size_t(const Camera&)>& max_batch,
                              const std::function<void(size_t begin, size_t end, const RenderedViews&)>& use);

// Per Gaussian, its blending weight alpha * T summed over every pixel of the view: how many pixels' worth
// of the image it makes. Read off the rasterizer's backward pass (the image is linear in the features, with
// the blending weights as coefficients), so both backends give it without a kernel of their own. N values,
// no gradient.
at::Tensor blending_weights(const GaussianModel& model, const Camera& camera);

}  // namespace gaps

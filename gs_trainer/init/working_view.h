#pragma once
// The resolution the dense stereo methods work at: a view brought down to a longest side.
#include <utility>
#include <vector>

#include <ATen/Tensor.h>
#include "gs_trainer/scene/camera.h"

namespace gaps {

// The view at no more than max_side pixels on its longest side (area averaging), image as HxWx3 float on the
// image's device; the camera and image themselves when they are small enough already.
std::pair<Camera, at::Tensor> working_view(const Camera& camera, const at::Tensor& image, int max_side);

// working_view of every view, in order.
struct WorkingViews {
  std::vector<Camera> cameras;
  std::vector<at::Tensor> images;
};
WorkingViews working_views(const std::vector<Camera>& cameras, const std::vector<at::Tensor>& images, int max_side);

}  // namespace gaps

#pragma once
// The resolution the dense stereo methods work at: a view brought down to a longest side.
#include <utility>

#include <ATen/Tensor.h>
#include "gs_trainer/scene/camera.h"

namespace gaps {

// The view at no more than max_side pixels on its longest side (area averaging), image as HxWx3 float on the
// image's device; the camera and image themselves when they are small enough already.
std::pair<Camera, at::Tensor> working_view(const Camera& camera, const at::Tensor& image, int max_side);

}  // namespace gaps

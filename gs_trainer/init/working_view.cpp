#include "gs_trainer/init/working_view.h"

#include <algorithm>
#include <cmath>

#include <ATen/ATen.h>

namespace gaps {

std::pair<Camera, at::Tensor> working_view(const Camera& camera, const at::Tensor& image, int max_side) {
  const at::Tensor img = image.to(at::kFloat);
  const double scale = std::min(1.0, static_cast<double>(max_side) / std::max(camera.width, camera.height));
  if (scale >= 1.0) return {camera, img.contiguous()};
  const int w = std::max(1, static_cast<int>(std::lround(camera.width * scale)));
  const int h = std::max(1, static_cast<int>(std::lround(camera.height * scale)));
  const at::Tensor chw = img.permute({2, 0, 1}).unsqueeze(0);
  const at::Tensor small = at::adaptive_avg_pool2d(chw, {h, w}).squeeze(0).permute({1, 2, 0}).contiguous();
  return {camera.resized(w, h), small};
}

WorkingViews working_views(const std::vector<Camera>& cameras, const std::vector<at::Tensor>& images, int max_side) {
  WorkingViews views;
  for (size_t i = 0; i < cameras.size(); ++i) {
    auto [camera, image] = working_view(cameras[i], images[i], max_side);
    views.cameras.push_back(camera);
    views.images.push_back(image);
  }
  return views;
}

}  // namespace gaps

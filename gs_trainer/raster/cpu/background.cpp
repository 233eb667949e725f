// The background compositing on the CPU, in ATen operations.
#include <ATen/ATen.h>

#include "gs_trainer/raster/rasterize_backend.h"

namespace gaps::backend {

at::Tensor over_background_forward_cpu(const at::Tensor& features, const at::Tensor& alpha,
                                       const at::Tensor& background) {
  return features.narrow(2, 0, 3) + (1 - alpha).unsqueeze(2) * background.view({1, 1, 3});
}

BackgroundGrads over_background_backward_cpu(const at::Tensor& g_rgb, const at::Tensor& background, int64_t channels) {
  const at::Tensor g_alpha =
      (g_rgb * background.view({1, 1, 3})).sum_to_size({g_rgb.size(0), g_rgb.size(1), 1}).squeeze(2).neg();
  return {at::constant_pad_nd(g_rgb, {0, channels - 3}), g_alpha};
}

}  // namespace gaps::backend

#include "gs_trainer/eval/image_stats.h"

#include <ATen/ATen.h>

namespace gaps {

at::Tensor greyscale(const at::Tensor& image) {
  TORCH_CHECK(image.dim() >= 3 && image.size(-1) == 3, "expected an HxWx3 image (or a batch of them), got shape ",
              image.sizes());
  const at::Tensor x = image.is_floating_point() ? image : image.to(at::kFloat);
  return 0.299 * x.select(-1, 0) + 0.587 * x.select(-1, 1) + 0.114 * x.select(-1, 2);
}

double total_variation(const at::Tensor& image) {
  const at::Tensor grey = greyscale(image).to(at::kDouble);
  const int64_t h = grey.size(0), w = grey.size(1);
  at::Tensor gx = at::zeros_like(grey), gy = at::zeros_like(grey);
  if (w > 2) gx.narrow(1, 1, w - 2).copy_((grey.narrow(1, 2, w - 2) - grey.narrow(1, 0, w - 2)) * 0.5);
  if (h > 2) gy.narrow(0, 1, h - 2).copy_((grey.narrow(0, 2, h - 2) - grey.narrow(0, 0, h - 2)) * 0.5);
  return at::sqrt(gx.square() + gy.square()).sum().item<double>();
}

}  // namespace gaps

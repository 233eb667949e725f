#pragma once
// Statistics of one image that several parts read: the GAPS scores (luma) and the automatic Gaussian
// budget (total variation). Images are H×W×3 in [0, 1].
#include <ATen/core/Tensor.h>

namespace gaps {

// Luma (Rec. 601 weights, which sum to 1) of an H×W×3 image: H×W (of a B×H×W×3 batch: B×H×W).
at::Tensor greyscale(const at::Tensor& image);

// Σ_p |∇I(p)| of an H x W x 3 image (grey = 0.299 R + 0.587 G + 0.114 B); the gradient is the central
// difference inside the image and zero on its border rows/columns.
double total_variation(const at::Tensor& image);

}  // namespace gaps

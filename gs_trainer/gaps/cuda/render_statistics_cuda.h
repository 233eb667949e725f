#pragma once
// render_statistics (scores.h) on the GPU in one pass over the pixels, for scores.cpp to pick for CUDA tensors.
// Only builds with CUDA kernels (GAPS_CUDA_KERNELS) define it.
#include <ATen/Tensor.h>

namespace gaps::backend {

// images B×H×W×3 (clamped to [0, 1] here; the first three channels of a contiguous B×H×W×C tensor are read in
// place), alphas B×H×W, float32 CUDA: per image the sums over its pixels, B×5
// doubles: alpha, normalised local entropy over `bins` grey levels, alpha >= coverage_threshold (0 or 1), luma,
// luma².
at::Tensor render_statistics_sums_cuda(const at::Tensor& images, const at::Tensor& alphas, int bins,
                                       double coverage_threshold);

}  // namespace gaps::backend

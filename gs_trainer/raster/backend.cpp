#include "gs_trainer/raster/backend.h"

#include <ATen/ops/empty.h>
#include <c10/util/Exception.h>

namespace gaps::backend {
namespace {

// The CPU pass sums |dL/dmean2d| in the same per-Gaussian records as the other gradients, so it has no
// variant without them.
RasterGrads rasterize_backward_cpu_entry(const TileBins& bins, const at::Tensor& means2d, const at::Tensor& conics,
                                         const at::Tensor& opacities, const at::Tensor& features,
                                         const RasterOutput& forward, const at::Tensor& g_features,
                                         const at::Tensor& g_alpha, bool /*absolute_grads*/) {
  return rasterize_backward_cpu(bins, means2d, conics, opacities, features, forward, g_features, g_alpha);
}

// In the order of RasterBackend's members; every entry has its own type, so a misplaced one does not compile.
constexpr RasterBackend kCpu{
    project_forward_cpu,
    project_backward_cpu,
    shade_forward_cpu,
    shade_backward_cpu,
    bin_tiles_cpu,
    project_views_forward_cpu,
    shade_views_forward_cpu,
    rasterize_views_forward_cpu,
    rasterize_forward_cpu,
    rasterize_backward_cpu_entry,
    ssim_forward_cpu,
    ssim_backward_cpu,
    over_background_forward_cpu,
    over_background_backward_cpu,
    photometric_forward_cpu,
    photometric_backward_cpu,
};

#if defined(GAPS_CUDA_KERNELS)
constexpr RasterBackend kCudaTable{
    project_forward_cuda,
    project_backward_cuda,
    shade_forward_cuda,
    shade_backward_cuda,
    bin_tiles_cuda,
    project_views_forward_cuda,
    shade_views_forward_cuda,
    rasterize_views_forward_cuda,
    rasterize_forward_cuda,
    rasterize_backward_cuda,
    ssim_forward_cuda,
    ssim_backward_cuda,
    over_background_forward_cuda,
    over_background_backward_cuda,
    photometric_forward_cuda,
    photometric_backward_cuda,
};
constexpr const RasterBackend* kCuda = &kCudaTable;
#else
constexpr const RasterBackend* kCuda = nullptr;
#endif

}  // namespace

const RasterBackend& raster_backend(const c10::Device& device) {
  if (!device.is_cuda()) return kCpu;
  TORCH_CHECK(kCuda != nullptr, "gaps was built without CUDA kernels (GAPS_CUDA=OFF or no nvcc): use --device cpu");
  return *kCuda;
}

RasterOutput empty_raster_output(int height, int width, int channels, const at::TensorOptions& options) {
  RasterOutput out;
  out.features = at::empty({height, width, channels}, options);
  out.alpha = at::empty({height, width}, options);
  out.final_T = at::empty({height, width}, options);
  out.n_contrib = at::empty({height, width}, options.dtype(at::kInt));
  return out;
}

}  // namespace gaps::backend

#pragma once
// The stages of rasterize_backend.h and the SSIM passes and loss of ssim_backend.h for one device, as a table: the
// autograd wrappers pick a table by the device of their input, and backend.cpp is the one file that knows
// whether this build has CUDA kernels.
#include <c10/core/Device.h>

#include "gs_trainer/raster/rasterize_backend.h"
#include "gs_trainer/raster/ssim_backend.h"

namespace gaps::backend {

// Each entry has the signature of its CPU function, except rasterize_backward, whose flag only CUDA reads.
struct RasterBackend {
  decltype(&project_forward_cpu) project_forward;
  decltype(&project_backward_cpu) project_backward;
  decltype(&shade_forward_cpu) shade_forward;
  decltype(&shade_backward_cpu) shade_backward;
  decltype(&bin_tiles_cpu) bin_tiles;
  decltype(&project_views_forward_cpu) project_views_forward;
  decltype(&shade_views_forward_cpu) shade_views_forward;
  decltype(&rasterize_views_forward_cpu) rasterize_views_forward;
  decltype(&rasterize_forward_cpu) rasterize_forward;
  // `absolute_grads` = false allows leaving RasterGrads::means2d_abs undefined.
  RasterGrads (*rasterize_backward)(const TileBins& bins, const at::Tensor& means2d, const at::Tensor& conics,
                                    const at::Tensor& opacities, const at::Tensor& features,
                                    const RasterOutput& forward, const at::Tensor& g_features,
                                    const at::Tensor& g_alpha, bool absolute_grads);
  decltype(&ssim_forward_cpu) ssim_forward;
  decltype(&ssim_backward_cpu) ssim_backward;
  decltype(&over_background_forward_cpu) over_background_forward;
  decltype(&over_background_backward_cpu) over_background_backward;
  decltype(&photometric_forward_cpu) photometric_forward;
  decltype(&photometric_backward_cpu) photometric_backward;
};

// The CUDA table for CUDA devices, the CPU one for every other; c10::Error for a CUDA device in a build
// without CUDA kernels.
const RasterBackend& raster_backend(const c10::Device& device);

}  // namespace gaps::backend

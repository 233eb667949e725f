// Front-to-back compositing on the GPU, as in 3DGS / gsplat: one 16x16 thread block per tile, one thread
// per pixel. The block walks its tile's depth-sorted list in batches of 256 Gaussians staged in shared
// memory; each thread composites its pixel with exactly the CPU's rules (cpu/rasterize_forward.cpp):
// skip alpha < 1/255, clamp alpha at 0.99, stop before the transmittance falls below 1e-4, and record
// how far the list was walked (n_contrib) for the backward pass. Several views of one size composite in one
// launch: the grid's rows are the views' tile rows one view after another, and view v writes image v of the
// stacked outputs.
#include <ATen/core/Tensor.h>
#include <ATen/cuda/CUDAContext.h>
#include <ATen/ops/empty.h>
#include <c10/cuda/CUDAGuard.h>

#include "gs_trainer/raster/cuda/cuda_common.h"
#include "gs_trainer/raster/rasterize_backend.h"

namespace gaps::backend {
namespace {

constexpr int kTile = raster::kTileSize;
constexpr int kBlock = kTile * kTile;

struct ForwardArgs : CompositeInputs {
  int tiles_y;  // of one view
  float* __restrict__ out_features;
  float* __restrict__ out_alpha;
  float* __restrict__ out_final_T;
  int32_t* __restrict__ out_n_contrib;
};

template <int CMAX>
__global__ void __launch_bounds__(kBlock) rasterize_forward_kernel(ForwardArgs a) {
  const int tile = blockIdx.y * a.tiles_x + blockIdx.x;
  const int view = blockIdx.y / a.tiles_y;
  const int px = blockIdx.x * kTile + threadIdx.x, py = (blockIdx.y - view * a.tiles_y) * kTile + threadIdx.y;
  const int thread = threadIdx.y * kTile + threadIdx.x;
  const bool inside = px < a.width && py < a.height;
  const float cx = static_cast<float>(px) + 0.5f, cy = static_cast<float>(py) + 0.5f;

  __shared__ StagedSplat s_splat[kBlock];
  __shared__ __align__(16) float s_feat[kBlock * CMAX];

  const int begin = a.ranges[2 * tile], end = a.ranges[2 * tile + 1];
  float T = 1.f;
  float acc[CMAX];
  for (int ch = 0; ch < CMAX; ++ch) acc[ch] = 0.f;
  int last = 0;
  bool done = !inside;  // threads past the image edge only help stage batches

  for (int batch_start = begin; batch_start < end; batch_start += kBlock) {
    // Also the barrier that lets this batch overwrite the previous one.
    if (__syncthreads_count(done) == kBlock) break;
    const int k = batch_start + thread;
    if (k < end) {
      const int g = a.ids[k];
      s_splat[thread] = stage_splat(a, g);
      for (int ch = 0; ch < CMAX; ++ch)
        s_feat[thread * CMAX + ch] = ch < a.channels ? a.features[static_cast<int64_t>(g) * a.channels + ch] : 0.f;
    }
    __syncthreads();
    const int batch = min(kBlock, end - batch_start);
    for (int j = 0; !done && j < batch; ++j) {
      const StagedSplat splat = s_splat[j];
      float alpha, gauss, dx, dy;
      const float power = staged_power(splat, cx, cy, dx, dy);
      if (power < splat.conic_c_opacity.z ||
          !raster::alpha_from_power_host_rounding(power, splat.conic_c_opacity.y, alpha, gauss))
        continue;
      const float next = T * (1 - alpha);
      if (next < static_cast<float>(raster::kMinTransmittance)) {
        done = true;
        break;
      }
      const float w = alpha * T;
      for (int ch = 0; ch < CMAX; ++ch) acc[ch] += w * s_feat[j * CMAX + ch];
      T = next;
      last = batch_start + j - begin + 1;
    }
  }
  if (!inside) return;
  const int64_t pix = (static_cast<int64_t>(view) * a.height + py) * a.width + px;
  for (int ch = 0; ch < CMAX; ++ch)
    if (ch < a.channels) a.out_features[pix * a.channels + ch] = acc[ch];
  a.out_alpha[pix] = 1 - T;
  a.out_final_T[pix] = T;
  a.out_n_contrib[pix] = last;
}

}  // namespace

namespace {

// Composites `views` views stacked view-major with their bins over views × tiles: outputs (views · height) × width.
RasterOutput composite(const TileBins& bins, int views, const at::Tensor& means2d_in, const at::Tensor& conics_in,
                       const at::Tensor& opacities_in, const at::Tensor& features_in, int width, int height) {
  check_raster_inputs({&means2d_in, &conics_in, &opacities_in, &features_in});
  const c10::cuda::CUDAGuard guard(means2d_in.device());
  const auto means2d = means2d_in.contiguous(), conics = conics_in.contiguous();
  const auto opacities = opacities_in.contiguous(), features = features_in.contiguous();
  const auto ranges = bins.tile_ranges.contiguous(), ids = bins.gaussian_ids.contiguous();
  const int channels = static_cast<int>(features.size(1));
  const auto opts = features.options();
  // Every pixel is written by the kernel, so no clearing pass is needed.
  RasterOutput out = empty_raster_output(views * height, width, channels, opts);

  const int tiles_x = (width + kTile - 1) / kTile, tiles_y = (height + kTile - 1) / kTile;
  const ForwardArgs args{composite_inputs(width, height, tiles_x, ranges, ids, means2d, conics, opacities, features),
                         tiles_y,
                         out.features.data_ptr<float>(),
                         out.alpha.data_ptr<float>(),
                         out.final_T.data_ptr<float>(),
                         out.n_contrib.data_ptr<int32_t>()};
  dispatch_channels(channels, [&](auto cmax) {
    rasterize_forward_kernel<decltype(cmax)::value>
        <<<dim3(tiles_x, views * tiles_y), dim3(kTile, kTile), 0, at::cuda::getCurrentCUDAStream()>>>(args);
  });
  C10_CUDA_KERNEL_LAUNCH_CHECK();
  return out;
}

}  // namespace

RasterOutput rasterize_forward_cuda(const TileBins& bins, const at::Tensor& means2d, const at::Tensor& conics,
                                    const at::Tensor& opacities, const at::Tensor& features, int width, int height) {
  return composite(bins, 1, means2d, conics, opacities, features, width, height);
}

RasterOutput rasterize_views_forward_cuda(int views, const at::Tensor& means2d, const at::Tensor& conics,
                                          const at::Tensor& opacities, const at::Tensor& radii,
                                          const at::Tensor& depths, const at::Tensor& features, int width, int height) {
  const TileBins bins = bin_tiles_views_cuda(views, means2d, conics, opacities, radii, depths, width, height);
  return composite(bins, views, means2d, conics, opacities, features, width, height);
}

}  // namespace gaps::backend

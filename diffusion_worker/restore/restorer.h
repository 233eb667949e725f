#pragma once
// Restoration of a render by Real-ESRGAN: the render is shrunk by a factor (area averaging), super-resolved 4x
// and resized back to its exact size. Shrunk 4x, a heavily blurred render is close to a sharp low-resolution
// image, from which the network synthesises sharp full-resolution detail; but the shrink also discards what
// detail the render has finer than 4 pixels. Shrunk less (2x), or not at all (super-resolved 4x, then shrunk 4x),
// the network works as a same-resolution restorer of mildly blurred renders (Real-ESRGAN was trained on degraded
// photographs: blur, noise and compression-like artefacts), at 4x or 16x the compute.
#include <cstdint>

#include <ATen/Tensor.h>
#include "diffusion_worker/restore/rrdbnet.h"

namespace gaps::restore {

// How the low-resolution image is fed to the network: whole (tile 0), or in tile x tile pieces, each run with
// tile_pad pixels of its surroundings (cropped off its output) so that seams stay invisible, which bounds the
// memory of large renders.
struct TileSettings {
  int64_t tile = 0;
  int64_t tile_pad = 10;
};

// x: N x C x h x w on the network's device and dtype; N x C x 4h x 4w.
at::Tensor super_resolve(const RrdbNet& net, const at::Tensor& x, const TileSettings& tiles);

// The side the network is given of a render's side shrunk by `downscale` (>= 1): round(side / downscale), at
// least 1 (halves round away from zero).
int64_t low_resolution_side(int64_t side, int downscale);

// image: H x W x 3 float on the CPU, in [0, 1]. Area-downscaled by `downscale` (1: not at all), super-resolved
// on `device` in `dtype` (the network's), resized to H x W (area averaging where the 4x output is at least as
// large in both directions, else bilinear) and clamped to [0, 1]: H x W x 3 float32 on the CPU.
at::Tensor restore_image(const RrdbNet& net, const at::Tensor& image, int downscale, at::Device device,
                         at::ScalarType dtype, const TileSettings& tiles);

}  // namespace gaps::restore

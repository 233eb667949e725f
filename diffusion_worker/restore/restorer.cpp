#include "diffusion_worker/restore/restorer.h"

#include <algorithm>
#include <cmath>

#include <ATen/ATen.h>
#include <opencv2/core.hpp>
#include <opencv2/imgproc.hpp>

namespace gaps::restore {
namespace {

// An H x W x 3 float32 contiguous CPU tensor resized by OpenCV (which reads and writes it in place).
at::Tensor resize(const at::Tensor& image, int64_t height, int64_t width, int interpolation) {
  if (image.size(0) == height && image.size(1) == width) return image;
  const cv::Mat in(static_cast<int>(image.size(0)), static_cast<int>(image.size(1)), CV_32FC3, image.data_ptr());
  at::Tensor out = at::empty({height, width, 3}, image.options());
  cv::Mat result(static_cast<int>(height), static_cast<int>(width), CV_32FC3, out.data_ptr());
  cv::resize(in, result, result.size(), 0, 0, interpolation);
  return out;
}

}  // namespace

int64_t low_resolution_side(int64_t side, int downscale) {
  return std::max<int64_t>(1, std::llround(static_cast<double>(side) / downscale));
}

at::Tensor super_resolve(const RrdbNet& net, const at::Tensor& x, const TileSettings& tiles) {
  const int64_t h = x.size(2), w = x.size(3), s = RrdbNet::kScale;
  if (tiles.tile <= 0 || (h <= tiles.tile && w <= tiles.tile)) return net(x);
  at::Tensor out = at::empty({x.size(0), net.config().out_channels, h * s, w * s}, x.options());
  for (int64_t y0 = 0; y0 < h; y0 += tiles.tile) {
    for (int64_t x0 = 0; x0 < w; x0 += tiles.tile) {
      const int64_t y1 = std::min(y0 + tiles.tile, h), x1 = std::min(x0 + tiles.tile, w);
      const int64_t py0 = std::max<int64_t>(0, y0 - tiles.tile_pad), px0 = std::max<int64_t>(0, x0 - tiles.tile_pad);
      const int64_t py1 = std::min(h, y1 + tiles.tile_pad), px1 = std::min(w, x1 + tiles.tile_pad);
      const at::Tensor piece = net(x.slice(2, py0, py1).slice(3, px0, px1));
      out.slice(2, y0 * s, y1 * s)
          .slice(3, x0 * s, x1 * s)
          .copy_(piece.slice(2, (y0 - py0) * s, (y1 - py0) * s).slice(3, (x0 - px0) * s, (x1 - px0) * s));
    }
  }
  return out;
}

at::Tensor restore_image(const RrdbNet& net, const at::Tensor& image, int downscale, at::Device device,
                         at::ScalarType dtype, const TileSettings& tiles) {
  const int64_t height = image.size(0), width = image.size(1);
  const at::Tensor full = image.to(at::kCPU, at::kFloat).contiguous();
  const at::Tensor small =
      resize(full, low_resolution_side(height, downscale), low_resolution_side(width, downscale), cv::INTER_AREA);
  const at::Tensor x = small.permute({2, 0, 1}).unsqueeze(0).to(device, dtype);
  const at::Tensor y = super_resolve(net, x, tiles).squeeze(0).permute({1, 2, 0}).to(at::kCPU, at::kFloat).contiguous();
  const bool shrinking = y.size(0) >= height && y.size(1) >= width;
  return resize(y, height, width, shrinking ? cv::INTER_AREA : cv::INTER_LINEAR).clamp(0, 1).contiguous();
}

}  // namespace gaps::restore

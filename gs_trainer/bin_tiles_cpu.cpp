// Tile binning on the CPU: every visible Gaussian is listed in each 16x16 tile its 3-sigma footprint
// touches, and each tile's list is sorted front to back (ties broken by index, so results are deterministic).
#include <algorithm>
#include <vector>

#include <ATen/ATen.h>
#include <ATen/Dispatch.h>
#include <ATen/Parallel.h>

#include "gs_trainer/rasterize_backend.h"

namespace gaps::backend {
namespace {

struct TileRect {
  int x0, y0, x1, y1;  // [x0, x1) x [y0, y1) in tiles
};

template <typename T> TileRect tile_rect(T mx, T my, int radius, int tiles_x, int tiles_y) {
  const T r = T(radius);
  auto clampi = [](int v, int hi) { return std::min(std::max(v, 0), hi); };
  const int ts = raster::kTileSize;
  return {clampi(static_cast<int>(std::floor((mx - r) / ts)), tiles_x),
          clampi(static_cast<int>(std::floor((my - r) / ts)), tiles_y),
          clampi(static_cast<int>(std::ceil((mx + r) / ts)), tiles_x),
          clampi(static_cast<int>(std::ceil((my + r) / ts)), tiles_y)};
}

template <typename T>
TileBins bin_impl(const at::Tensor& means2d, const at::Tensor& radii, const at::Tensor& depths, int width,
                  int height) {
  const int tiles_x = (width + raster::kTileSize - 1) / raster::kTileSize;
  const int tiles_y = (height + raster::kTileSize - 1) / raster::kTileSize;
  const int num_tiles = tiles_x * tiles_y;
  const int64_t n = means2d.size(0);
  const T* m2 = means2d.data_ptr<T>();
  const int32_t* rad = radii.data_ptr<int32_t>();
  const T* dep = depths.data_ptr<T>();

  std::vector<int32_t> counts(num_tiles + 1, 0);
  for (int64_t i = 0; i < n; ++i) {
    if (rad[i] <= 0) continue;
    const TileRect r = tile_rect(m2[2 * i], m2[2 * i + 1], rad[i], tiles_x, tiles_y);
    for (int ty = r.y0; ty < r.y1; ++ty)
      for (int tx = r.x0; tx < r.x1; ++tx) ++counts[ty * tiles_x + tx + 1];
  }
  for (int t = 0; t < num_tiles; ++t) counts[t + 1] += counts[t];

  at::Tensor ids = at::empty({counts[num_tiles]}, at::kInt);
  at::Tensor ranges = at::empty({num_tiles, 2}, at::kInt);
  int32_t* idp = ids.data_ptr<int32_t>();
  int32_t* rp = ranges.data_ptr<int32_t>();
  std::vector<int32_t> cursor(counts.begin(), counts.end() - 1);
  for (int64_t i = 0; i < n; ++i) {
    if (rad[i] <= 0) continue;
    const TileRect r = tile_rect(m2[2 * i], m2[2 * i + 1], rad[i], tiles_x, tiles_y);
    for (int ty = r.y0; ty < r.y1; ++ty)
      for (int tx = r.x0; tx < r.x1; ++tx) idp[cursor[ty * tiles_x + tx]++] = static_cast<int32_t>(i);
  }
  at::parallel_for(0, num_tiles, 16, [&](int64_t begin, int64_t end) {
    for (int64_t t = begin; t < end; ++t) {
      rp[2 * t] = counts[t];
      rp[2 * t + 1] = counts[t + 1];
      std::sort(idp + counts[t], idp + counts[t + 1], [&](int32_t a, int32_t b) {
        return dep[a] < dep[b] || (dep[a] == dep[b] && a < b);
      });
    }
  });
  return {ids, ranges};
}

}  // namespace

TileBins bin_tiles_cpu(const at::Tensor& means2d, const at::Tensor& radii, const at::Tensor& depths, int width,
                       int height) {
  TileBins bins;
  AT_DISPATCH_FLOATING_TYPES(means2d.scalar_type(), "bin_tiles_cpu", [&] {
    bins = bin_impl<scalar_t>(means2d.contiguous(), radii.contiguous(), depths.contiguous(), width, height);
  });
  return bins;
}

}  // namespace gaps::backend

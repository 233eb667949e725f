// Tile binning on the CPU: every visible Gaussian is listed in each 16x16 tile its footprint touches
// (raster::tile_footprint, row by row as raster::for_each_footprint_tile walks it), and each tile's list is
// sorted front to back (ties broken by index, so results are deterministic).
//
// Instead of sorting every tile's list, the visible Gaussians are sorted once by (depth, index) and then
// written to their tiles in that order, which leaves every list sorted. The writing is split into
// consecutive chunks of the sorted order, one per thread; each chunk's entries go after those of the
// chunks before it in every tile, so the result does not depend on the number of threads.
#include <algorithm>
#include <vector>

#include <ATen/ATen.h>
#include <ATen/Dispatch.h>
#include <ATen/Parallel.h>

#include "gs_trainer/raster/rasterize_backend.h"

namespace gaps::backend {
namespace {

// The visible Gaussians (radius > 0) in (depth, index) order.
template <typename T>
std::vector<int32_t> depth_order(int64_t n, const int32_t* rad, const T* dep) {
  struct Key {
    T depth;
    int32_t id;
  };
  std::vector<Key> keys;
  keys.reserve(static_cast<size_t>(n));
  for (int64_t i = 0; i < n; ++i)
    if (rad[i] > 0) keys.push_back({dep[i], static_cast<int32_t>(i)});
  std::sort(keys.begin(), keys.end(),
            [](const Key& a, const Key& b) { return a.depth < b.depth || (a.depth == b.depth && a.id < b.id); });
  std::vector<int32_t> order(keys.size());
  for (size_t i = 0; i < keys.size(); ++i) order[i] = keys[i].id;
  return order;
}

template <typename T>
TileBins bin_impl(const at::Tensor& means2d, const at::Tensor& conics, const at::Tensor& opacities,
                  const at::Tensor& radii, const at::Tensor& depths, int width, int height) {
  const int tiles_x = (width + raster::kTileSize - 1) / raster::kTileSize;
  const int tiles_y = (height + raster::kTileSize - 1) / raster::kTileSize;
  const int num_tiles = tiles_x * tiles_y;
  const T* m2 = means2d.data_ptr<T>();
  const T* con = conics.data_ptr<T>();
  const T* op = opacities.data_ptr<T>();
  const int32_t* rad = radii.data_ptr<int32_t>();
  const std::vector<int32_t> order = depth_order(means2d.size(0), rad, depths.data_ptr<T>());
  const int64_t visible = static_cast<int64_t>(order.size());

  // Calls body(tile, gaussian) for every tile of every Gaussian of chunk c, in depth order.
  const int64_t chunks = std::max<int64_t>(1, std::min<int64_t>(at::get_num_threads(), visible / 1024));
  auto for_each_entry = [&](int64_t c, auto&& body) {
    for (int64_t j = visible * c / chunks; j < visible * (c + 1) / chunks; ++j) {
      const int32_t i = order[j];
      const raster::TileFootprint f = raster::tile_footprint<T>(
          {m2[2 * i], m2[2 * i + 1]}, {con[3 * i], con[3 * i + 1], con[3 * i + 2]}, op[i], rad[i], tiles_x, tiles_y);
      raster::for_each_footprint_tile(f, [&](int tx, int ty) { body(ty * tiles_x + tx, i); });
    }
  };

  // cursor[c][t]: first the number of chunk c's entries in tile t, then the slot of the next one.
  std::vector<std::vector<int32_t>> cursor(chunks, std::vector<int32_t>(num_tiles, 0));
  at::parallel_for(0, chunks, 1, [&](int64_t c_begin, int64_t c_end) {
    for (int64_t c = c_begin; c < c_end; ++c) for_each_entry(c, [&](int t, int32_t) { ++cursor[c][t]; });
  });
  at::Tensor ranges = at::empty({num_tiles, 2}, at::kInt);
  int32_t* rp = ranges.data_ptr<int32_t>();
  int32_t total = 0;
  for (int t = 0; t < num_tiles; ++t) {
    rp[2 * t] = total;
    for (int64_t c = 0; c < chunks; ++c) {
      const int32_t count = cursor[c][t];
      cursor[c][t] = total;
      total += count;
    }
    rp[2 * t + 1] = total;
  }

  at::Tensor ids = at::empty({total}, at::kInt);
  int32_t* idp = ids.data_ptr<int32_t>();
  at::parallel_for(0, chunks, 1, [&](int64_t c_begin, int64_t c_end) {
    for (int64_t c = c_begin; c < c_end; ++c) for_each_entry(c, [&](int t, int32_t i) { idp[cursor[c][t]++] = i; });
  });
  return {ids, ranges};
}

}  // namespace

TileBins bin_tiles_cpu(const at::Tensor& means2d, const at::Tensor& conics, const at::Tensor& opacities,
                       const at::Tensor& radii, const at::Tensor& depths, int width, int height) {
  TileBins bins;
  AT_DISPATCH_FLOATING_TYPES(means2d.scalar_type(), "bin_tiles_cpu", [&] {
    bins =
        bin_impl<scalar_t>(means2d.contiguous(), conics.contiguous(), opacities.to(means2d.scalar_type()).contiguous(),
                           radii.contiguous(), depths.contiguous(), width, height);
  });
  return bins;
}

}  // namespace gaps::backend

#pragma once
// What the CPU forward and backward tile kernels share (scalar part; the vector part is
// rasterize_tile_simd.h): the packed per-Gaussian record they read, with what the conservative
// "which rows of this tile can the Gaussian reach" test needs, and the tiles' geometry. CPU only.
//
// Exactness: that test only drops rows where the per-pixel test of eval_alpha (power > 0 or alpha < 1/255
// skips) would fail for every pixel; the kernels evaluate the per-pixel test for every pixel of the rows
// it keeps.
#include <algorithm>
#include <cmath>
#include <cstdint>
#include <vector>

#include <ATen/Parallel.h>

#include "gs_trainer/raster/raster_math.h"

namespace gaps::backend::tile {

constexpr int kRows = raster::kTileSize;

// One Gaussian as the tile loops read it, in one cache line (in float).
template <typename T>
struct alignas(16 * sizeof(T)) Splat {
  T mx, my;   // 2D mean
  T a, b, c;  // conic
  T opacity;
  // Where alpha can reach kMinAlpha: in the row of pixel centres at height py (dy = my - py), the centres px
  // with |px - (mx + shear dy)| <= sqrt(h2 - shrink dy^2); reached_row_bits (rasterize_tile_simd.h)
  // adds the safety margins. h2 < 0: nowhere; h2 = inf: anywhere (no culling).
  T h2, shrink, shear;
  // Float only: [lo, hi] bands of power outside which the simd::exp used for float gives the same skip
  // (alpha < kMinAlpha) and clamp (alpha >= kMaxAlpha) decisions as eval_alpha's exp (see
  // rasterize_tile_simd.h). Empty (NaN) where the Gaussian contributes nowhere.
  T near_min[2], near_max[2];
};

// The powers p where a = opacity * exp(p) is within 1e-6 (relative) of `threshold` as eval_alpha compares
// it (rounded to T), rounded outwards. Both exps are within a few 1e-7 of exact: beyond the band, a and
// the threshold compare the same way whichever exp computed a.
template <typename T>
void threshold_band(double threshold, double opacity, T band[2]) {
  const double p = std::log(double(T(threshold)) / opacity);
  band[0] = std::nextafter(T(p - 1e-6), T(-INFINITY));
  band[1] = std::nextafter(T(p + 1e-6), T(INFINITY));
}

// Computed in double so that the margins, not rounding, decide how conservative the culling is.
template <typename T>
Splat<T> make_splat(const T* mean2d, const T* conic, T opacity) {
  Splat<T> s{mean2d[0], mean2d[1], conic[0], conic[1],         conic[2],        opacity,
             T(-1),     T(0),      T(0),     {T(NAN), T(NAN)}, {T(NAN), T(NAN)}};
  const double a = conic[0], b = conic[1], c = conic[2], o = opacity;
  // NaN/inf Gaussians never contributed (the former per-row span test rejected them), and a Gaussian with
  // opacity <= 1/255 cannot reach the threshold anywhere (alpha <= opacity where power <= 0).
  if (!(std::isfinite(mean2d[0]) && std::isfinite(mean2d[1]) && std::isfinite(a) && std::isfinite(b) &&
        std::isfinite(c) && std::isfinite(o) && opacity * T(255) > T(1)))
    return s;
  // power = -0.5 (a dx^2 + 2 b dx dy + c dy^2) >= L := log(1 / (255 o)), dx = mx - px, is
  //   (dx + b dy / a)^2 <= -2 L / a - (det / a^2) dy^2.
  // The per-pixel test evaluates power in float, with an error that grows with the conic's condition
  // number; up to det >= 1e-4 a c it stays well inside the one-pixel margins. Worse conditioned (or
  // indefinite) conics get no culling: the per-pixel test alone decides there.
  threshold_band(raster::kMinAlpha, o, s.near_min);
  threshold_band(raster::kMaxAlpha, o, s.near_max);
  const double det = a * c - b * b, L = std::log(1.0 / (255.0 * o));
  if (!(a > 0 && c > 0 && det > 1e-4 * a * c)) {
    s.h2 = T(INFINITY);
    return s;
  }
  s.h2 = T(-2.0 * L / a);
  s.shrink = T(det / (a * a));
  s.shear = T(b / a);
  return s;
}

template <typename T>
std::vector<Splat<T>> make_splats(int64_t n, const T* means2d, const T* conics, const T* opacities) {
  std::vector<Splat<T>> splats(static_cast<size_t>(n));
  at::parallel_for(0, n, 2048, [&](int64_t begin, int64_t end) {
    for (int64_t i = begin; i < end; ++i) splats[i] = make_splat(means2d + 2 * i, conics + 3 * i, opacities[i]);
  });
  return splats;
}

// A tile's pixel rectangle: [x0, x0 + w) x [y0, y0 + h).
struct TileRect {
  int x0, y0, w, h;
};

inline TileRect tile_rect(int64_t tile, int tiles_x, int width, int height) {
  const int x0 = static_cast<int>(tile % tiles_x) * raster::kTileSize;
  const int y0 = static_cast<int>(tile / tiles_x) * raster::kTileSize;
  return {x0, y0, std::min(raster::kTileSize, width - x0), std::min(raster::kTileSize, height - y0)};
}

}  // namespace gaps::backend::tile

// The tiles a Gaussian is listed in (raster::tile_footprint, walked row by row by for_each_footprint_tile)
// against brute force: every pixel where eval_alpha accepts the Gaussian, in double and in float, must lie in a
// listed tile, and the row spans must be no wider than the bounding box and tighter for tilted ellipses.
#include <cmath>
#include <cstdint>
#include <iostream>
#include <random>
#include <set>
#include <utility>
#include <vector>

#include <ATen/ATen.h>
#include <gtest/gtest.h>

#include "gs_trainer/raster/raster_math.h"
#include "gs_trainer/raster/rasterize_backend.h"
#include "tests/raster_test_util.h"

namespace gaps {
namespace {

using raster::kTileSize;

// A projected Gaussian as the rasterizer receives it (float, like the training path).
struct Splat {
  raster::Vec2<float> mean;
  raster::Sym2<float> conic;
  float opacity;
  int radius;
};

// The conic of a 2D covariance with standard deviations (s1, s2) along an axis at angle theta, dilated by
// kLowPass and inverted in float the way finish_projection does; radius as finish_projection computes it.
Splat splat_from_covariance(float mx, float my, double s1, double s2, double theta, float opacity) {
  const double co = std::cos(theta), si = std::sin(theta);
  const float a = static_cast<float>(s1 * s1 * co * co + s2 * s2 * si * si + raster::kLowPass);
  const float b = static_cast<float>((s1 * s1 - s2 * s2) * co * si);
  const float c = static_cast<float>(s1 * s1 * si * si + s2 * s2 * co * co + raster::kLowPass);
  const float det = a * c - b * b;
  const float mid = 0.5f * (a + c), disc = mid * mid - det;
  const float lambda1 = mid + std::sqrt(disc > 0.1f ? disc : 0.1f);
  return {{mx, my}, {c / det, -b / det, a / det}, opacity, static_cast<int>(std::ceil(3 * std::sqrt(lambda1)))};
}

// Random Gaussians: means in and around the image, sizes from under a pixel to larger than the image,
// any orientation and elongation, opacities from just under 1/255 to 1; some with their radius cut short
// and some with conics that bound no ellipse.
std::vector<Splat> random_splats(int n, int width, int height, uint32_t seed) {
  std::mt19937 rng(seed);
  std::uniform_real_distribution<double> u(0.0, 1.0);
  std::vector<Splat> out;
  for (int i = 0; i < n; ++i) {
    const float mx = static_cast<float>(-0.4 * width + 1.8 * width * u(rng));
    const float my = static_cast<float>(-0.4 * height + 1.8 * height * u(rng));
    const double s1 = 0.2 * std::pow(1000.0, u(rng)), s2 = s1 * std::pow(0.002, u(rng));
    const float opacity = static_cast<float>(u(rng) < 0.3 ? (0.9 + 3 * u(rng)) / 255.0 : u(rng));
    Splat s = splat_from_covariance(mx, my, s1, s2, 2 * M_PI * u(rng), opacity);
    const double kind = u(rng);
    if (kind < 0.1) s.radius = 1 + static_cast<int>(s.radius * u(rng));  // a 3-sigma square inside the ellipse
    if (kind > 0.97) s.conic.b = std::sqrt(s.conic.a * s.conic.c) * static_cast<float>(1 + u(rng));  // det < 0
    if (kind > 0.985) s.conic = {-s.conic.a, 0.f, -s.conic.c};  // negative definite
    out.push_back(s);
  }
  return out;
}

template <typename T>
raster::TileFootprint footprint(const Splat& s, int tiles_x, int tiles_y) {
  return raster::tile_footprint<T>({T(s.mean.x), T(s.mean.y)}, {T(s.conic.a), T(s.conic.b), T(s.conic.c)}, T(s.opacity),
                                   s.radius, tiles_x, tiles_y);
}

template <typename T>
bool accepts(const Splat& s, int i, int j) {
  T alpha, gauss, dx, dy;
  return raster::eval_alpha<T>({T(s.mean.x), T(s.mean.y)}, {T(s.conic.a), T(s.conic.b), T(s.conic.c)}, T(s.opacity),
                               T(i + 0.5), T(j + 0.5), alpha, gauss, dx, dy);
}

// The listed tiles in the order they are visited, checking that the walk and the count agree.
std::vector<std::pair<int, int>> listed_tiles(const raster::TileFootprint& f) {
  std::vector<std::pair<int, int>> tiles;
  raster::for_each_footprint_tile(f, [&](int tx, int ty) { tiles.emplace_back(ty, tx); });
  EXPECT_EQ(static_cast<int64_t>(tiles.size()), raster::footprint_tile_count(f));
  return tiles;
}

int64_t rect_area(const raster::TileRect& r) { return int64_t{r.x1 - r.x0} * (r.y1 - r.y0); }

// Every pixel of the bounding box that eval_alpha accepts lies in a listed tile; the tiles are the box's,
// visited row by row, each once.
template <typename T>
void expect_covers_accepted_pixels(const Splat& s, int width, int height, int index) {
  const int tiles_x = (width + kTileSize - 1) / kTileSize, tiles_y = (height + kTileSize - 1) / kTileSize;
  const raster::TileFootprint f = footprint<T>(s, tiles_x, tiles_y);
  const auto tiles = listed_tiles(f);
  const std::set<std::pair<int, int>> listed(tiles.begin(), tiles.end());
  ASSERT_EQ(listed.size(), tiles.size()) << "splat " << index << ": a tile listed twice";
  ASSERT_TRUE(std::is_sorted(tiles.begin(), tiles.end())) << "splat " << index << ": not row by row";
  for (const auto& [ty, tx] : tiles) {
    ASSERT_TRUE(ty >= f.rect.y0 && ty < f.rect.y1 && tx >= f.rect.x0 && tx < f.rect.x1)
        << "splat " << index << ": tile (" << tx << ", " << ty << ") outside the bounding box";
  }
  const raster::TileRect& r = f.rect;
  for (int j = r.y0 * kTileSize; j < std::min(r.y1 * kTileSize, height); ++j) {
    for (int i = r.x0 * kTileSize; i < std::min(r.x1 * kTileSize, width); ++i) {
      if (!accepts<double>(s, i, j) && !accepts<float>(s, i, j)) continue;
      ASSERT_TRUE(listed.count({j / kTileSize, i / kTileSize}))
          << "splat " << index << " (mean " << s.mean.x << ", " << s.mean.y << "; conic " << s.conic.a << ", "
          << s.conic.b << ", " << s.conic.c << "; opacity " << s.opacity << ", radius " << s.radius
          << ") reaches pixel (" << i << ", " << j << ") of an unlisted tile";
    }
  }
}

TEST(TileFootprint, ListsEveryTileWhereAlphaIsAccepted) {
  const int width = 203, height = 157;  // partial tiles on the right and at the bottom
  const auto splats = random_splats(5000, width, height, 5);
  for (size_t k = 0; k < splats.size(); ++k) {
    expect_covers_accepted_pixels<float>(splats[k], width, height, static_cast<int>(k));
    expect_covers_accepted_pixels<double>(splats[k], width, height, static_cast<int>(k));
    if (HasFatalFailure()) return;
  }
}

// Pixels an opacity just under 1/255 can never make visible list nothing, as in the bounding box.
TEST(TileFootprint, InvisibleOpacityListsNothing) {
  const Splat s = splat_from_covariance(50, 50, 10, 3, 0.5, 0.99f / 255.0f);
  const raster::TileFootprint f = footprint<float>(s, 8, 8);
  EXPECT_EQ(rect_area(f.rect), 0);
  EXPECT_EQ(raster::footprint_tile_count(f), 0);
}

// A conic that bounds no ellipse keeps the whole 3-sigma square, row by row.
TEST(TileFootprint, UnboundedConicKeepsTheSquare) {
  Splat s = splat_from_covariance(100, 90, 10, 3, 0.5, 0.5f);
  s.conic.b = 2 * std::sqrt(s.conic.a * s.conic.c);
  const raster::TileFootprint f = footprint<float>(s, 16, 16);
  EXPECT_EQ(f.rect.x0, (100 - s.radius) / kTileSize);
  EXPECT_EQ(f.rect.y1, (90 + s.radius + kTileSize - 1) / kTileSize);
  EXPECT_EQ(raster::footprint_tile_count(f), rect_area(f.rect));
}

TEST(TileFootprint, ThinDiagonalGaussianListsFewerTilesThanItsBox) {
  const Splat s = splat_from_covariance(128, 128, 40, 0.5, M_PI / 4, 0.9f);
  const raster::TileFootprint f = footprint<float>(s, 16, 16);
  EXPECT_GE(rect_area(f.rect), 49);  // its box is 7 x 7 tiles or more
  EXPECT_LT(raster::footprint_tile_count(f), rect_area(f.rect) / 2);
}

// Centred on a tile corner, a small axis-aligned ellipse reaches into each of the four tiles around it.
TEST(TileFootprint, SmallAxisAlignedGaussianListsItsBox) {
  const Splat s = splat_from_covariance(96, 64, 3, 2.5, 0, 0.9f);
  const raster::TileFootprint f = footprint<float>(s, 16, 16);
  EXPECT_EQ(rect_area(f.rect), 4);
  EXPECT_EQ(raster::footprint_tile_count(f), rect_area(f.rect));
}

// The binning lists exactly the footprints' tiles. Logs how many (tile, Gaussian) pairs the row spans save
// over the bounding boxes for a random scene of small, anisotropic Gaussians seen at LLFF's 504 x 378.
TEST(TileFootprint, BinningListsTheFootprints) {
  const int width = 504, height = 378, n = 20000;
  at::manual_seed(3);
  const auto opts = at::TensorOptions().dtype(at::kFloat);
  test::RandomScene s;
  s.means = at::rand({n, 3}, opts) * at::tensor({4.0, 3.0, 4.0}, opts) - at::tensor({2.0, 1.5, -1.0}, opts);
  s.quats = at::randn({n, 4}, opts);
  s.scales = at::exp(at::rand({n, 3}, opts) * 4.0 - 6.0);
  s.opacities = at::rand({n}, opts);
  test::place_camera(s, width, height, opts);
  const auto p = backend::project_forward_cpu(s.means, s.quats, s.scales, s.viewmat, s.K);
  const auto bins = backend::bin_tiles_cpu(p.means2d, p.conics, s.opacities, p.radii, p.depths, width, height);

  const int tiles_x = (width + kTileSize - 1) / kTileSize, tiles_y = (height + kTileSize - 1) / kTileSize;
  const auto m2 = p.means2d.accessor<float, 2>();
  const auto con = p.conics.accessor<float, 2>();
  const auto op = s.opacities.accessor<float, 1>();
  const auto rad = p.radii.accessor<int32_t, 1>();
  std::vector<int64_t> per_tile(tiles_x * tiles_y, 0);
  int64_t boxes = 0;
  for (int i = 0; i < n; ++i) {
    if (rad[i] <= 0) continue;
    const auto f = raster::tile_footprint<float>({m2[i][0], m2[i][1]}, {con[i][0], con[i][1], con[i][2]}, op[i], rad[i],
                                                 tiles_x, tiles_y);
    boxes += rect_area(f.rect);
    raster::for_each_footprint_tile(f, [&](int tx, int ty) { ++per_tile[ty * tiles_x + tx]; });
  }
  const auto ranges = bins.tile_ranges.accessor<int32_t, 2>();
  for (int t = 0; t < tiles_x * tiles_y; ++t) EXPECT_EQ(ranges[t][1] - ranges[t][0], per_tile[t]) << "tile " << t;
  const int64_t pairs = bins.gaussian_ids.numel();
  EXPECT_LE(pairs, boxes);
  std::cout << "(tile, Gaussian) pairs: " << pairs << " listed by row spans, " << boxes << " in bounding boxes\n";
}

}  // namespace
}  // namespace gaps

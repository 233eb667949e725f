// eval_alpha (raster_math.h) for a whole tile row segment at once, for one instruction set: included by
// the kernel headers inside simd_multiversion.h (no include guard, no system includes).
//
// A tile row of 16 pixels is kSegments<T> vectors ("segments"). The terms of the Gaussian's power that
// only depend on the column are computed once per (tile, Gaussian), those that only depend on the row
// once per row; every operation keeps the association and rounding of eval_alpha, so `power` is exactly
// eval_alpha's. In double precision exp is std::exp, so alpha is too. In single precision eval_alpha
// computes exp in double (the C library's exp(double), rounded to float); simd::exp is within ~2 ulp of
// that, and where such a difference could change a decision (alpha within a few ulp of kMinAlpha or
// kMaxAlpha) the lanes are recomputed the same way, so skips and clamps are exactly eval_alpha's
// (the CUDA kernels rely on the same contract, see alpha_from_power_host_rounding in raster_math.h).
#include "gs_trainer/raster/cpu/simd_ops.h"

namespace gaps::backend::tile::GAPS_SIMD_NS {

using simd::GAPS_SIMD_NS::Mask;
using simd::GAPS_SIMD_NS::Vec;

template <typename T>
constexpr int kSegments = kRows / simd::GAPS_SIMD_NS::kWidth<T>;

// Pixel-centre x coordinates of each segment of a tile row starting at x0.
template <typename T>
GAPS_SIMD_INLINE void segment_centres(int x0, Vec<T> (&px)[kSegments<T>]) {
  for (int sg = 0; sg < kSegments<T>; ++sg)
    px[sg] = simd::GAPS_SIMD_NS::iota<T>(T(x0 + sg * simd::GAPS_SIMD_NS::kWidth<T>) + T(0.5));
}

// Bit ly set: row ly of tile r has a pixel centre where the Gaussian's alpha may reach kMinAlpha
// (conservatively, see Splat): the band of the row is widened by one pixel and taken from one pixel
// nearer to the mean, plus 0.1%.
template <typename T>
GAPS_SIMD_INLINE uint32_t reached_row_bits(const Splat<T>& s, const TileRect& r) {
  namespace ops = simd::GAPS_SIMD_NS;
  constexpr int W = ops::kWidth<T>;
  const T x_first = T(r.x0) + T(0.5), x_last = T(r.x0 + r.w) - T(0.5);
  uint32_t rows = 0;
  for (int first = 0; first < r.h; first += W) {
    const Vec<T> dy = s.my - ops::iota<T>(T(r.y0 + first) + T(0.5));
    const Vec<T> dy_in = ops::max(ops::abs<T>(dy) - T(1), Vec<T>{});
    const Vec<T> h2 = s.h2 - s.shrink * dy_in * dy_in;
    const Vec<T> h = ops::sqrt(ops::max(h2, Vec<T>{})) * T(1.001) + T(1);
    const Vec<T> centre = s.mx + s.shear * dy;
    const Mask<T> reached = (h2 >= T(0)) & (centre + h >= x_first) & (centre - h <= x_last);
    rows |= ops::bits<T>(reached) << first;
  }
  return rows & ((1u << r.h) - 1);
}

// The column terms dx, a dx dx and b dx of one Gaussian over the tile's columns.
template <typename T>
struct SplatColumns {
  Vec<T> dx[kSegments<T>], a_dx_dx[kSegments<T>], b_dx[kSegments<T>];

  GAPS_SIMD_INLINE SplatColumns(const Splat<T>& s, const Vec<T> (&px)[kSegments<T>]) {
    for (int sg = 0; sg < kSegments<T>; ++sg) {
      dx[sg] = s.mx - px[sg];
      a_dx_dx[sg] = s.a * dx[sg] * dx[sg];
      b_dx[sg] = s.b * dx[sg];
    }
  }
};

// The row terms dy and c dy dy of one Gaussian at pixel-centre row py.
template <typename T>
struct SplatRow {
  T dy, c_dy_dy;
  GAPS_SIMD_INLINE SplatRow(const Splat<T>& s, T py) : dy(s.my - py), c_dy_dy(s.c * dy * dy) {}
};

template <typename T>
struct SegmentAlpha {
  Vec<T> gauss;          // exp(power)
  Vec<T> opacity_gauss;  // opacity * gauss, before the clamp
  Vec<T> alpha;          // min(kMaxAlpha, opacity_gauss)
  Mask<T> hit;           // not skipped: power <= 0 and alpha >= kMinAlpha
};

// Which of eval_alpha's decisions must be exactly eval_alpha's: the skip (alpha < kMinAlpha) always; the
// clamp (alpha >= kMaxAlpha) only where it matters beyond rounding, i.e. for the gradient (which a clamped
// alpha does not have). In the forward pass the clamp only moves alpha by a few ulp.
enum class Exact { kSkip, kSkipAndClamp };

// gauss = exp(power) in double, rounded to float, in the lanes of `lanes`. Rarely needed, and out of line
// so that its library calls (which clobber every vector register) stay out of the callers' hot loops.
__attribute__((noinline, cold)) inline void exact_exp_lanes(const Vec<float>& power, const Mask<float>& lanes,
                                                            Vec<float>& gauss) {
  for (int i = 0; i < simd::GAPS_SIMD_NS::kWidth<float>; ++i)
    if (lanes[i]) gauss[i] = static_cast<float>(std::exp(static_cast<double>(power[i])));
}

// Where simd::exp could decide differently from eval_alpha's exp (power in a band around an alpha
// threshold, see Splat::near_min), recomputes gauss as eval_alpha does.
template <Exact kExact>
GAPS_SIMD_INLINE void exact_exp_near_thresholds(const Splat<float>& s, const Vec<float>& power, Vec<float>& gauss) {
  Mask<float> near = (power >= s.near_min[0]) & (power <= s.near_min[1]);
  if constexpr (kExact == Exact::kSkipAndClamp) near |= (power >= s.near_max[0]) & (power <= s.near_max[1]);
  if (__builtin_expect(simd::GAPS_SIMD_NS::any<float>(near), 0)) {
    // Copies, so that the caller's values need not live in memory for the call.
    const Vec<float> power_copy = power;
    const Mask<float> near_copy = near;
    Vec<float> gauss_copy = gauss;
    exact_exp_lanes(power_copy, near_copy, gauss_copy);
    gauss = gauss_copy;
  }
}
// Double precision already uses std::exp.
template <Exact kExact>
GAPS_SIMD_INLINE void exact_exp_near_thresholds(const Splat<double>&, const Vec<double>&, Vec<double>&) {}

template <Exact kExact, typename T>
GAPS_SIMD_INLINE SegmentAlpha<T> eval_alpha(const Splat<T>& s, const SplatColumns<T>& cols, int sg,
                                            const SplatRow<T>& row) {
  SegmentAlpha<T> r;
  Vec<T> b_dx_dy = cols.b_dx[sg] * row.dy;
  simd::GAPS_SIMD_NS::no_contraction(b_dx_dy);  // eval_alpha rounds the product before subtracting it
  const Vec<T> power = T(-0.5) * (cols.a_dx_dx[sg] + row.c_dy_dy) - b_dx_dy;
  r.gauss = simd::GAPS_SIMD_NS::exp(power);
  exact_exp_near_thresholds<kExact>(s, power, r.gauss);
  r.opacity_gauss = s.opacity * r.gauss;
  // min(opacity_gauss, kMaxAlpha) yields kMaxAlpha for NaN, like eval_alpha's `a < kMaxAlpha ? a : kMaxAlpha`.
  r.alpha = simd::GAPS_SIMD_NS::min(r.opacity_gauss, simd::GAPS_SIMD_NS::splat(T(raster::kMaxAlpha)));
  r.hit = ~(power > T(0)) & (r.alpha >= T(raster::kMinAlpha));
  return r;
}

}  // namespace gaps::backend::tile::GAPS_SIMD_NS

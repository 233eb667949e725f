// The forward tile kernel of cpu/rasterize_forward.cpp for one instruction set: included there through
// simd_multiversion.h (no include guard, no system includes; ForwardArgs comes from the includer).
#include "gs_trainer/raster/cpu/rasterize_tile_simd.h"

namespace gaps::backend::GAPS_SIMD_NS {

using namespace simd::GAPS_SIMD_NS;
using namespace tile::GAPS_SIMD_NS;
using tile::kRows;

// The compositing state of one tile, one vector per row segment (index ly * kSegments + segment).
// A pixel composites while its transmittance is positive (live pixels keep T >= kMinTransmittance): a
// saturated pixel, or one outside the image, has trans 0, and its final transmittance is in final_T. This
// spares a separate "alive" mask (and the compiler's conversions between vector masks and mask registers).
template <typename T>
struct ForwardTileState {
  static constexpr int kSegs = kSegments<T>;
  Vec<T> trans[kRows * kSegs];    // transmittance so far; 0 once the pixel stopped
  Vec<T> final_T[kRows * kSegs];  // transmittance of the pixels that stopped
  Mask<T> last[kRows * kSegs];    // n_contrib: tile-list entries walked up to the last contributor
  Buffer<T> acc;                  // accumulated features: acc[ch * kRows * kSegs + segment index]
  bool segment_live[kRows * kSegs];
  uint32_t live_rows = 0;  // bit per row with any live pixel

  ForwardTileState(const tile::TileRect& r, int channels) : acc(static_cast<size_t>(channels) * kRows * kSegs) {
    for (int ly = 0; ly < kRows; ++ly) {
      for (int sg = 0; sg < kSegs; ++sg) {
        const int i = ly * kSegs + sg;
        const Mask<T> inside = ly < r.h ? first_lanes<T>(r.w - sg * kWidth<T>) : Mask<T>{};
        trans[i] = select<T>(inside, splat(T(1)), Vec<T>{});
        final_T[i] = Vec<T>{};
        last[i] = Mask<T>{};
        segment_live[i] = any<T>(inside);
        if (segment_live[i]) live_rows |= 1u << ly;
      }
    }
  }

  // The pixels `lanes` of segment i stop with transmittance `t`; keeps the live flags up to date.
  GAPS_SIMD_INLINE void stop(int ly, int i, const Mask<T>& lanes, const Vec<T>& t) {
    final_T[i] = select<T>(lanes, t, final_T[i]);
    trans[i] = select<T>(lanes, Vec<T>{}, trans[i]);
    if (any<T>(trans[i] > T(0))) return;
    segment_live[i] = false;
    bool row_live = false;
    for (int sg = 0; sg < kSegs; ++sg) row_live |= segment_live[ly * kSegs + sg];
    if (!row_live) live_rows &= ~(1u << ly);
  }

  // The transmittance of every pixel after compositing.
  GAPS_SIMD_INLINE Vec<T> transmittance(int i) const { return select<T>(trans[i] > T(0), trans[i], final_T[i]); }
};

// Composites one Gaussian (tile-list position `entry`, features f) onto segment i of row ly.
template <typename T>
GAPS_SIMD_INLINE void composite_segment(ForwardTileState<T>& st, int ly, int i, const SegmentAlpha<T>& a, const T* f,
                                        int channels, int32_t entry) {
  const Vec<T> trans = st.trans[i];
  const Vec<T> next = trans * (T(1) - a.alpha);
  const Mask<T> hit = a.hit & (trans > T(0));
  // A pixel stops before its transmittance would fall below the threshold; this Gaussian is not composited.
  const Mask<T> composite = hit & (next >= T(raster::kMinTransmittance));
  const Mask<T> stop = hit & (next < T(raster::kMinTransmittance));
  // The weight, 0 where this Gaussian is not composited (adding 0 * f leaves the finite sums unchanged).
  const Vec<T> w = select<T>(composite, a.alpha * trans, Vec<T>{});
  constexpr int kTileSegs = kRows * ForwardTileState<T>::kSegs;
  for (int ch = 0; ch < channels; ++ch) st.acc[static_cast<size_t>(ch) * kTileSegs + i] += w * f[ch];
  st.trans[i] = select<T>(composite, next, trans);
  st.last[i] = composite ? Mask<T>{} + (entry + 1) : st.last[i];
  if (any<T>(stop)) st.stop(ly, i, stop, trans);
}

template <typename T>
GAPS_SIMD_INLINE void composite_tile(int64_t tile_index, const ForwardArgs<T>& in) {
  constexpr int kSegs = kSegments<T>, W = kWidth<T>;
  const tile::TileRect r = tile::tile_rect(tile_index, in.tiles_x, in.width, in.height);
  const int C = in.channels;
  ForwardTileState<T> st(r, C);
  Vec<T> px[kSegs];
  segment_centres<T>(r.x0, px);
  const int32_t begin = in.ranges[2 * tile_index], end = in.ranges[2 * tile_index + 1];
  for (int32_t k = begin; k < end && st.live_rows != 0; ++k) {
    const int32_t g = in.ids[k];
    const tile::Splat<T>& s = in.splats[g];
    uint32_t rows = reached_row_bits(s, r) & st.live_rows;
    if (rows == 0) continue;
    const T* f = in.feat + static_cast<int64_t>(g) * C;
    const SplatColumns<T> cols(s, px);
    for (; rows != 0; rows &= rows - 1) {
      const int ly = __builtin_ctz(rows);
      const SplatRow<T> row(s, T(r.y0 + ly) + T(0.5));
      for (int sg = 0; sg < kSegs; ++sg) {
        const int i = ly * kSegs + sg;
        if (!st.segment_live[i]) continue;
        composite_segment(st, ly, i, eval_alpha<Exact::kSkip>(s, cols, sg, row), f, C, k - begin);
      }
    }
  }
  for (int ly = 0; ly < r.h; ++ly) {
    for (int lx = 0; lx < r.w; ++lx) {
      const int i = ly * kSegs + lx / W, lane = lx % W;
      const int64_t pix = static_cast<int64_t>(r.y0 + ly) * in.width + r.x0 + lx;
      for (int ch = 0; ch < C; ++ch)
        in.out_feat[pix * C + ch] = st.acc[static_cast<size_t>(ch) * kRows * kSegs + i][lane];
      const T final_T = st.transmittance(i)[lane];
      in.out_alpha[pix] = 1 - final_T;
      in.out_final_T[pix] = final_T;
      in.out_n_contrib[pix] = static_cast<int32_t>(st.last[i][lane]);
    }
  }
}

// The entry point of this copy.
template <typename T>
void composite_tile_entry(int64_t tile_index, const ForwardArgs<T>& in) {
  composite_tile(tile_index, in);
}

}  // namespace gaps::backend::GAPS_SIMD_NS

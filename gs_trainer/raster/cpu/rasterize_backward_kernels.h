// The backward tile kernel of cpu/rasterize_backward.cpp for one instruction set: included there through
// simd_multiversion.h (no include guard, no system includes; BackwardArgs and kFixed come from the
// includer).
#include "gs_trainer/raster/cpu/rasterize_tile_simd.h"

namespace gaps::backend::GAPS_SIMD_NS {

using namespace simd::GAPS_SIMD_NS;
using namespace tile::GAPS_SIMD_NS;
using tile::kRows;

// The per-pixel state of one tile, one vector per row segment (index ly * kSegments + segment).
template <typename T>
struct BackwardTileState {
  static constexpr int kSegs = kSegments<T>, kTileSegs = kRows * kSegs;
  Vec<T> trans[kTileSegs];             // transmittance in front of the Gaussians walked so far (back to front)
  Mask<T> contrib[kTileSegs];          // n_contrib of the forward pass (0 outside the image)
  Vec<T> g_alpha_T[kTileSegs];         // dL/dalpha_out * final_T
  int32_t segment_contrib[kTileSegs];  // max n_contrib over the segment
  int32_t row_contrib[kRows];          // max n_contrib over the row
  int32_t max_contrib = 0;
  Buffer<T> g_out;   // dL/dfeatures_out, channel-major: [ch * kTileSegs + segment index]
  Buffer<T> behind;  // features composited behind the current Gaussian, same layout
  Buffer<T> g_feat;  // the current entry's feature gradient when the channel count is not fixed
  Buffer<T> sums;    // the current entry's gradient, one vector per value of the entry

  // Bit ly set: row ly has pixels that walked entry `entry` in the forward pass.
  GAPS_SIMD_INLINE uint32_t rows_walking(int32_t entry) const {
    uint32_t rows = 0;
    for (int ly = 0; ly < kRows; ++ly) rows |= uint32_t(row_contrib[ly] > entry) << ly;
    return rows;
  }

  BackwardTileState(const tile::TileRect& r, const BackwardArgs<T>& in)
      : g_out(static_cast<size_t>(in.channels) * kTileSegs),
        behind(static_cast<size_t>(in.channels) * kTileSegs),
        g_feat(in.channels),
        sums(kFixed + in.channels) {
    const int C = in.channels, W = kWidth<T>;
    for (int i = 0; i < kTileSegs; ++i) {
      trans[i] = splat(T(1));
      contrib[i] = Mask<T>{};
      g_alpha_T[i] = Vec<T>{};
    }
    for (int ly = 0; ly < r.h; ++ly) {
      for (int lx = 0; lx < r.w; ++lx) {
        const int i = ly * kSegs + lx / W, lane = lx % W;
        const int64_t pix = static_cast<int64_t>(r.y0 + ly) * in.width + r.x0 + lx;
        trans[i][lane] = in.final_T[pix];
        contrib[i][lane] = in.n_contrib[pix];
        g_alpha_T[i][lane] = in.g_alpha[pix] * in.final_T[pix];
        for (int ch = 0; ch < C; ++ch) g_out[static_cast<size_t>(ch) * kTileSegs + i][lane] = in.g_feat[pix * C + ch];
      }
    }
    for (int ly = 0; ly < kRows; ++ly) {
      row_contrib[ly] = 0;
      for (int sg = 0; sg < kSegs; ++sg) {
        const int i = ly * kSegs + sg;
        segment_contrib[i] = 0;
        for (int lane = 0; lane < W; ++lane)
          segment_contrib[i] = std::max(segment_contrib[i], static_cast<int32_t>(contrib[i][lane]));
        row_contrib[ly] = std::max(row_contrib[ly], segment_contrib[i]);
      }
      max_contrib = std::max(max_contrib, row_contrib[ly]);
    }
  }
};

// One Gaussian's column terms of the gradient, besides those of SplatColumns.
template <typename T>
struct GradColumns {
  Vec<T> a_dx[kSegments<T>], neg_dx[kSegments<T>], neg_half_dx_dx[kSegments<T>];
  GAPS_SIMD_INLINE GradColumns(const tile::Splat<T>& s, const SplatColumns<T>& cols) {
    for (int sg = 0; sg < kSegments<T>; ++sg) {
      a_dx[sg] = s.a * cols.dx[sg];
      neg_dx[sg] = -cols.dx[sg];
      neg_half_dx_dx[sg] = T(-0.5) * cols.dx[sg] * cols.dx[sg];
    }
  }
};

// The per-lane sums of one entry's gradient. kChannels: the number of feature channels when known at
// compile time (the feature sums then live in registers), else 0 (they live in `buffer`).
template <typename T, int kChannels>
struct EntryGrads {
  Vec<T> mean_x{}, mean_y{}, conic_a{}, conic_b{}, conic_c{}, opacity{}, abs_mean_x{}, abs_mean_y{};
  Vec<T> feat[kChannels] = {};
  EntryGrads(Buffer<T>&, int) {}
};
template <typename T>
struct EntryGrads<T, 0> {
  Vec<T> mean_x{}, mean_y{}, conic_a{}, conic_b{}, conic_c{}, opacity{}, abs_mean_x{}, abs_mean_y{};
  Buffer<T>& feat;
  EntryGrads(Buffer<T>& buffer, int channels) : feat(buffer) {
    for (int ch = 0; ch < channels; ++ch) feat[ch] = Vec<T>{};
  }
};

// Undoes the compositing of one Gaussian (features f) on segment i, whose pixels `hit` it contributed
// to, and accumulates its gradients there: eval_alpha_vjp of raster_math.h, vectorised, with the sums
// over channels and the constant factors regrouped (which only changes rounding).
template <typename T, int kChannels>
GAPS_SIMD_INLINE void backward_segment(BackwardTileState<T>& st, int i, int sg, const Mask<T>& hit,
                                       const SegmentAlpha<T>& a, const tile::Splat<T>& s, const SplatColumns<T>& cols,
                                       const GradColumns<T>& gcols, const SplatRow<T>& row, const T* f, int channels,
                                       EntryGrads<T, kChannels>& acc) {
  using V = Vec<T>;
  constexpr int kTileSegs = BackwardTileState<T>::kTileSegs;
  const V inv_one_minus_alpha = reciprocal(T(1) - a.alpha);
  const V t = st.trans[i] * inv_one_minus_alpha;  // transmittance in front of this Gaussian
  st.trans[i] = select<T>(hit, t, st.trans[i]);
  const V alpha_t = a.alpha * t;
  // dL/dalpha = t sum_ch (f - behind) dL/dout  +  dL/dalpha_out final_T / (1 - alpha).
  V behind_term{};
  for (int ch = 0; ch < channels; ++ch) {
    const V g_out = st.g_out[static_cast<size_t>(ch) * kTileSegs + i];
    V& behind = st.behind[static_cast<size_t>(ch) * kTileSegs + i];
    const V f_minus_behind = f[ch] - behind;
    acc.feat[ch] = select<T>(hit, acc.feat[ch] + alpha_t * g_out, acc.feat[ch]);
    behind_term += f_minus_behind * g_out;
    behind = select<T>(hit, behind + a.alpha * f_minus_behind, behind);  // composite this Gaussian behind
  }
  const V g_alpha = behind_term * t + st.g_alpha_T[i] * inv_one_minus_alpha;
  // A clamped alpha has no gradient.
  const Mask<T> live = hit & ~(a.opacity_gauss >= T(raster::kMaxAlpha));
  const V g_power = a.opacity_gauss * g_alpha;
  const V minus_g_mx = g_power * (gcols.a_dx[sg] + s.b * row.dy);
  const V minus_g_my = g_power * (cols.b_dx[sg] + s.c * row.dy);
  acc.mean_x = select<T>(live, acc.mean_x - minus_g_mx, acc.mean_x);
  acc.mean_y = select<T>(live, acc.mean_y - minus_g_my, acc.mean_y);
  acc.abs_mean_x = select<T>(live, acc.abs_mean_x + abs<T>(minus_g_mx), acc.abs_mean_x);
  acc.abs_mean_y = select<T>(live, acc.abs_mean_y + abs<T>(minus_g_my), acc.abs_mean_y);
  acc.conic_a = select<T>(live, acc.conic_a + gcols.neg_half_dx_dx[sg] * g_power, acc.conic_a);
  acc.conic_b = select<T>(live, acc.conic_b + gcols.neg_dx[sg] * row.dy * g_power, acc.conic_b);
  acc.conic_c = select<T>(live, acc.conic_c + T(-0.5) * row.dy * row.dy * g_power, acc.conic_c);
  acc.opacity = select<T>(live, acc.opacity + a.gauss * g_alpha, acc.opacity);
}

// Walks the tile's list back to front from the last entry any pixel used, writing a gradient record for
// every entry that touched a pixel.
template <typename T, int kChannels>
GAPS_SIMD_INLINE void backward_tile(int64_t tile_index, const BackwardArgs<T>& in) {
  constexpr int kSegs = kSegments<T>;
  const tile::TileRect r = tile::tile_rect(tile_index, in.tiles_x, in.width, in.height);
  const int C = kChannels > 0 ? kChannels : in.channels;
  BackwardTileState<T> st(r, in);
  Vec<T> px[kSegs];
  segment_centres<T>(r.x0, px);
  const int32_t begin = in.ranges[2 * tile_index];
  TileRecords<T> records(in, tile_index);
  for (int32_t k = begin + st.max_contrib - 1; k >= begin; --k) {
    const int32_t entry = k - begin;
    const int32_t g = in.ids[k];
    const tile::Splat<T>& s = in.splats[g];
    uint32_t rows = reached_row_bits(s, r) & st.rows_walking(entry);
    if (rows == 0) continue;
    EntryGrads<T, kChannels> acc(st.g_feat, C);
    bool touched = false;
    const T* f = in.feat + static_cast<int64_t>(g) * C;
    const SplatColumns<T> cols(s, px);
    const GradColumns<T> gcols(s, cols);
    const Mask<T> walked = Mask<T>{} + entry;  // lanes with entry < n_contrib walked this entry
    for (; rows != 0; rows &= rows - 1) {
      const int ly = __builtin_ctz(rows);
      const SplatRow<T> row(s, T(r.y0 + ly) + T(0.5));
      for (int sg = 0; sg < kSegs; ++sg) {
        const int i = ly * kSegs + sg;
        if (st.segment_contrib[i] <= entry) continue;
        const SegmentAlpha<T> a = eval_alpha<Exact::kSkipAndClamp>(s, cols, sg, row);
        const Mask<T> hit = a.hit & (walked < st.contrib[i]);
        if (!any<T>(hit)) continue;
        backward_segment(st, i, sg, hit, a, s, cols, gcols, row, f, C, acc);
        touched = true;
      }
    }
    if (!touched) continue;  // no gradient, no record
    // The record layout of cpu/rasterize_backward.cpp: mean2d (2), conic (3), opacity (1), |mean2d| (2),
    // features (C).
    st.sums[0] = acc.mean_x;
    st.sums[1] = acc.mean_y;
    st.sums[2] = acc.conic_a;
    st.sums[3] = acc.conic_b;
    st.sums[4] = acc.conic_c;
    st.sums[5] = acc.opacity;
    st.sums[6] = acc.abs_mean_x;
    st.sums[7] = acc.abs_mean_y;
    for (int ch = 0; ch < C; ++ch) st.sums[kFixed + ch] = acc.feat[ch];
    sum_lanes<T>(&st.sums[0], kFixed + C, records.add(g));
  }
  records.finish();
}

// The entry point of this copy; the usual channel counts (colour, colour + depth) are compiled apart.
template <typename T>
void backward_tile_entry(int64_t tile_index, const BackwardArgs<T>& in) {
  switch (in.channels) {
    case 3:
      return backward_tile<T, 3>(tile_index, in);
    case 4:
      return backward_tile<T, 4>(tile_index, in);
    default:
      return backward_tile<T, 0>(tile_index, in);
  }
}

}  // namespace gaps::backend::GAPS_SIMD_NS

// SIMD vocabulary of the CPU tile kernels, for one instruction set: included (through a kernel header) by
// simd_multiversion.h once per GAPS_SIMD_NS, with GAPS_SIMD_BYTES the native vector width. No include
// guard and no system includes, on purpose (see simd_multiversion.h). Needs <cmath>, <cstdint>,
// <cstring>, <new>, <type_traits>, <utility> and, on x86-64, <immintrin.h>.
//
// A Vec<T> is one native register of lanes (16 floats with AVX-512, 8 with AVX2, 4 with SSE2); a Mask<T>
// has one integer lane (0 or -1) per lane of Vec<T>, as produced by vector comparisons.

namespace gaps::simd::GAPS_SIMD_NS {

constexpr int kVectorBytes = GAPS_SIMD_BYTES;

template <typename T>
struct Types;
template <>
struct Types<float> {
  typedef float Vec __attribute__((vector_size(kVectorBytes), aligned(kVectorBytes)));
  typedef int32_t Mask __attribute__((vector_size(kVectorBytes), aligned(kVectorBytes)));
};
template <>
struct Types<double> {
  typedef double Vec __attribute__((vector_size(kVectorBytes), aligned(kVectorBytes)));
  typedef int64_t Mask __attribute__((vector_size(kVectorBytes), aligned(kVectorBytes)));
};
template <typename T>
using Vec = typename Types<T>::Vec;
template <typename T>
using Mask = typename Types<T>::Mask;
template <typename T>
constexpr int kWidth = kVectorBytes / sizeof(T);  // lanes per vector

template <typename T>
GAPS_SIMD_INLINE Vec<T> splat(T x) {
  return Vec<T>{} + x;
}

// Lane i holds `start + i`.
template <typename T>
GAPS_SIMD_INLINE Vec<T> iota(T start) {
  Vec<T> v{};
  for (int i = 0; i < kWidth<T>; ++i) v[i] = start + T(i);
  return v;
}

// Lanes [0, n) set.
template <typename T>
GAPS_SIMD_INLINE Mask<T> first_lanes(int n) {
  Mask<T> m{};
  for (int i = 0; i < kWidth<T>; ++i) m[i] = i < n ? -1 : 0;
  return m;
}

template <typename T>
GAPS_SIMD_INLINE Vec<T> select(const Mask<T>& m, const Vec<T>& a, const Vec<T>& b) {
  return m ? a : b;
}

// True when any lane of the mask is set.
template <typename T>
GAPS_SIMD_INLINE bool any(const Mask<T>& m) {
#if defined(__x86_64__) && GAPS_SIMD_BYTES == 64
  return _mm512_test_epi32_mask(reinterpret_cast<__m512i>(m), reinterpret_cast<__m512i>(m)) != 0;
#elif defined(__x86_64__) && GAPS_SIMD_BYTES == 32
  return !_mm256_testz_si256(reinterpret_cast<__m256i>(m), reinterpret_cast<__m256i>(m));
#elif defined(__x86_64__) && GAPS_SIMD_BYTES == 16
  return _mm_movemask_epi8(reinterpret_cast<__m128i>(m)) != 0;
#else
  uint64_t words[sizeof(m) / sizeof(uint64_t)];
  std::memcpy(words, &m, sizeof(m));
  uint64_t r = 0;
  for (uint64_t w : words) r |= w;
  return r != 0;
#endif
}

// Bit i set where lane i of the mask is.
template <typename T>
GAPS_SIMD_INLINE uint32_t bits(const Mask<T>& m) {
#if defined(__x86_64__) && GAPS_SIMD_BYTES == 64
  if constexpr (sizeof(T) == 4)
    return _mm512_movepi32_mask(reinterpret_cast<__m512i>(m));
  else
    return _mm512_movepi64_mask(reinterpret_cast<__m512i>(m));
#elif defined(__x86_64__) && GAPS_SIMD_BYTES == 32
  if constexpr (sizeof(T) == 4)
    return _mm256_movemask_ps(reinterpret_cast<__m256>(m));
  else
    return _mm256_movemask_pd(reinterpret_cast<__m256d>(m));
#elif defined(__x86_64__) && GAPS_SIMD_BYTES == 16
  if constexpr (sizeof(T) == 4)
    return _mm_movemask_ps(reinterpret_cast<__m128>(m));
  else
    return _mm_movemask_pd(reinterpret_cast<__m128d>(m));
#else
  uint32_t r = 0;
  for (int i = 0; i < kWidth<T>; ++i) r |= uint32_t(m[i] != 0) << i;
  return r;
#endif
}

// Keeps the compiler from fusing the computation of x into a later multiply-add (FMA contraction), so
// that x is rounded exactly as written.
template <typename V>
GAPS_SIMD_INLINE void no_contraction(V& x) {
#if defined(__x86_64__)
  asm("" : "+v"(x));
#endif
}

// Sums the lanes of n vectors: out[j] = sum of the lanes of v[j]. The vectors are reduced kWidth at a
// time by a transposing tree (2 shuffles and 1 add per pair, rather than a full reduction per vector);
// the order of the additions is fixed, so results are deterministic. v is clobbered.
template <typename T, int kGroup, int... I>
GAPS_SIMD_INLINE Vec<T> fold_pairs(const Vec<T>& a, const Vec<T>& b, std::integer_sequence<int, I...>) {
  // The lanes of a and b hold groups of kGroup partial sums of one vector each; the result holds groups
  // of kGroup / 2: those of a's vectors, then those of b's.
  constexpr int W = kWidth<T>, kHalf = kGroup / 2;
  constexpr auto lo = [](int i) { return (i < W / 2 ? 0 : W) + (i % (W / 2)) / kHalf * kGroup + i % kHalf; };
#if defined(__clang__)
  return __builtin_shufflevector(a, b, lo(I)...) + __builtin_shufflevector(a, b, (lo(I) + kHalf)...);
#else
  const Mask<T> lo_index = {lo(I)...}, hi_index = {(lo(I) + kHalf)...};
  return __builtin_shuffle(a, b, lo_index) + __builtin_shuffle(a, b, hi_index);
#endif
}

// Folds batch[0, kGroup) (groups of kGroup partial sums) down to batch[0] (one sum per lane).
template <typename T, int kGroup>
GAPS_SIMD_INLINE void fold_batch(Vec<T>* batch) {
  if constexpr (kGroup > 1) {
    constexpr auto lanes = std::make_integer_sequence<int, kWidth<T>>();
    for (int k = 0; k < kGroup / 2; ++k) batch[k] = fold_pairs<T, kGroup>(batch[2 * k], batch[2 * k + 1], lanes);
    fold_batch<T, kGroup / 2>(batch);
  }
}

template <typename T>
GAPS_SIMD_INLINE void sum_lanes(Vec<T>* v, int n, T* out) {
  constexpr int W = kWidth<T>;
  for (int first = 0; first < n; first += W) {
    Vec<T> batch[W];
    for (int j = 0; j < W; ++j) batch[j] = first + j < n ? v[first + j] : Vec<T>{};
    fold_batch<T, W>(batch);
    for (int j = 0; j < W && first + j < n; ++j) out[first + j] = batch[0][j];
  }
}

// |v|: clears the sign bits.
template <typename T>
GAPS_SIMD_INLINE Vec<T> abs(const Vec<T>& v) {
  using Lane = typename std::remove_reference_t<decltype(Mask<T>{}[0])>;
  return reinterpret_cast<Vec<T>>(reinterpret_cast<Mask<T>>(v) & ~(Lane(1) << (8 * sizeof(Lane) - 1)));
}

// exp of each lane. Double precision calls std::exp per lane, so that the double path (which the gradient
// checks use) computes exactly what the scalar definition does.
GAPS_SIMD_INLINE Vec<double> exp(const Vec<double>& x) {
  Vec<double> r{};
  for (int i = 0; i < kWidth<double>; ++i) r[i] = std::exp(x[i]);
  return r;
}

// Lane-wise max(a, b) and min(a, b): a > b ? a : b and a < b ? a : b (so b where a lane is NaN).
GAPS_SIMD_INLINE Vec<float> max(const Vec<float>& a, const Vec<float>& b) {
#if defined(__x86_64__) && GAPS_SIMD_BYTES == 64
  return reinterpret_cast<Vec<float>>(_mm512_max_ps(reinterpret_cast<__m512>(a), reinterpret_cast<__m512>(b)));
#elif defined(__x86_64__) && GAPS_SIMD_BYTES == 32
  return reinterpret_cast<Vec<float>>(_mm256_max_ps(reinterpret_cast<__m256>(a), reinterpret_cast<__m256>(b)));
#else
  return select<float>(a > b, a, b);
#endif
}
GAPS_SIMD_INLINE Vec<float> min(const Vec<float>& a, const Vec<float>& b) {
#if defined(__x86_64__) && GAPS_SIMD_BYTES == 64
  return reinterpret_cast<Vec<float>>(_mm512_min_ps(reinterpret_cast<__m512>(a), reinterpret_cast<__m512>(b)));
#elif defined(__x86_64__) && GAPS_SIMD_BYTES == 32
  return reinterpret_cast<Vec<float>>(_mm256_min_ps(reinterpret_cast<__m256>(a), reinterpret_cast<__m256>(b)));
#else
  return select<float>(a < b, a, b);
#endif
}
GAPS_SIMD_INLINE Vec<double> max(const Vec<double>& a, const Vec<double>& b) { return select<double>(a > b, a, b); }
GAPS_SIMD_INLINE Vec<double> min(const Vec<double>& a, const Vec<double>& b) { return select<double>(a < b, a, b); }

// Single precision: Cephes' expf (Cody-Waite range reduction, degree-5 polynomial), within 1 ulp of the
// correctly rounded exp on [-87, 88] (checked exhaustively for every instruction set; with AVX-512 down to
// the smallest normal result). Below -87 it returns ~1e-38, 0 or a denormal depending on the instruction
// set, which the rasterizer never distinguishes (such alphas are far below 1/255). Not for NaN input.
GAPS_SIMD_INLINE Vec<float> exp(const Vec<float>& x_in) {
  using V = Vec<float>;
#if defined(__x86_64__) && GAPS_SIMD_BYTES == 64
  // vscalefps applies 2^n with proper underflow and overflow: no clamping, and one rounding instruction.
  const V x = x_in;
  const V n = reinterpret_cast<V>(_mm512_roundscale_ps(reinterpret_cast<__m512>(x * 1.44269504088896341f),
                                                       _MM_FROUND_TO_NEAREST_INT | _MM_FROUND_NO_EXC));
#else
  const V x = min(max(x_in, splat(-87.0f)), splat(88.0f));
  // n = round(x / ln 2) by the 1.5 * 2^23 trick (round to nearest).
  const V shifter = splat(12582912.0f);
  const V n = (x * 1.44269504088896341f + shifter) - shifter;
#endif
  // r = x - n ln 2, with ln 2 in two parts so that r is nearly exact.
  const V r = (x - n * 0.693359375f) - n * -2.12194440e-4f;
  V p = splat(1.9875691500e-4f);
  p = p * r + 1.3981999507e-3f;
  p = p * r + 8.3334519073e-3f;
  p = p * r + 4.1665795894e-2f;
  p = p * r + 1.6666665459e-1f;
  p = p * r + 5.0000001201e-1f;
  p = p * (r * r) + r + 1.0f;
#if defined(__x86_64__) && GAPS_SIMD_BYTES == 64
  return reinterpret_cast<V>(_mm512_scalef_ps(reinterpret_cast<__m512>(p), reinterpret_cast<__m512>(n)));
#else
  const Mask<float> bits = (__builtin_convertvector(n, Mask<float>) + 127) << 23;  // 2^n
  return p * reinterpret_cast<V>(bits);
#endif
}

GAPS_SIMD_INLINE Vec<float> sqrt(const Vec<float>& x) {
#if defined(__x86_64__) && GAPS_SIMD_BYTES == 64
  return reinterpret_cast<Vec<float>>(_mm512_sqrt_ps(reinterpret_cast<__m512>(x)));
#elif defined(__x86_64__) && GAPS_SIMD_BYTES == 32
  return reinterpret_cast<Vec<float>>(_mm256_sqrt_ps(reinterpret_cast<__m256>(x)));
#elif defined(__x86_64__) && GAPS_SIMD_BYTES == 16
  return reinterpret_cast<Vec<float>>(_mm_sqrt_ps(reinterpret_cast<__m128>(x)));
#else
  Vec<float> r{};
  for (int i = 0; i < kWidth<float>; ++i) r[i] = std::sqrt(x[i]);
  return r;
#endif
}
GAPS_SIMD_INLINE Vec<double> sqrt(const Vec<double>& x) {
#if defined(__x86_64__) && GAPS_SIMD_BYTES == 64
  return reinterpret_cast<Vec<double>>(_mm512_sqrt_pd(reinterpret_cast<__m512d>(x)));
#elif defined(__x86_64__) && GAPS_SIMD_BYTES == 32
  return reinterpret_cast<Vec<double>>(_mm256_sqrt_pd(reinterpret_cast<__m256d>(x)));
#elif defined(__x86_64__) && GAPS_SIMD_BYTES == 16
  return reinterpret_cast<Vec<double>>(_mm_sqrt_pd(reinterpret_cast<__m128d>(x)));
#else
  Vec<double> r{};
  for (int i = 0; i < kWidth<double>; ++i) r[i] = std::sqrt(x[i]);
  return r;
#endif
}

// 1 / x. Single precision: the hardware estimate refined by a Newton step (within ~1 ulp; no division,
// which is slow and poorly pipelined). Double precision: exact division.
GAPS_SIMD_INLINE Vec<double> reciprocal(const Vec<double>& x) { return 1.0 / x; }
GAPS_SIMD_INLINE Vec<float> reciprocal(const Vec<float>& x) {
#if defined(__x86_64__) && GAPS_SIMD_BYTES == 64
  const Vec<float> r = reinterpret_cast<Vec<float>>(_mm512_rcp14_ps(reinterpret_cast<__m512>(x)));
#elif defined(__x86_64__) && GAPS_SIMD_BYTES == 32
  const Vec<float> r = reinterpret_cast<Vec<float>>(_mm256_rcp_ps(reinterpret_cast<__m256>(x)));
#elif defined(__x86_64__) && GAPS_SIMD_BYTES == 16
  const Vec<float> r = reinterpret_cast<Vec<float>>(_mm_rcp_ps(reinterpret_cast<__m128>(x)));
#else
  const Vec<float> r = 1.0f / x;
#endif
  return r * (2.0f - x * r);
}

// A zero-initialised heap array of vectors with their alignment (std::vector would ignore it: GCC drops
// attributes of template arguments).
template <typename T>
class Buffer {
 public:
  explicit Buffer(size_t n)
      : data_(static_cast<Vec<T>*>(::operator new(n * sizeof(Vec<T>), std::align_val_t(kVectorBytes)))) {
    std::memset(static_cast<void*>(data_), 0, n * sizeof(Vec<T>));
  }
  ~Buffer() { ::operator delete(data_, std::align_val_t(kVectorBytes)); }
  Buffer(const Buffer&) = delete;
  Buffer& operator=(const Buffer&) = delete;
  Vec<T>& operator[](size_t i) { return data_[i]; }
  const Vec<T>& operator[](size_t i) const { return data_[i]; }

 private:
  Vec<T>* data_;
};

}  // namespace gaps::simd::GAPS_SIMD_NS

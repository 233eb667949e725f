#pragma once
// Run-time choice of instruction set for the CPU rasterizer's SIMD tile kernels.
//
// The library is built for baseline x86-64, so the kernels are compiled several times, each copy for
// one instruction set, and the caller picks the best copy the CPU runs. The kernels are written once
// with GCC/Clang vector extensions (simd_ops.h) in a header that simd_multiversion.h includes
// once per instruction set, each time in its own namespace (avx512, avx2, baseline) under a target
// pragma. (A target attribute on the entry function alone is not enough: GCC lowers the vector
// comparisons of an inline helper for the ISA the helper was parsed with, lane by lane, before inlining.)
#include <cstdlib>
#include <string>

#define GAPS_SIMD_INLINE inline __attribute__((always_inline))

namespace gaps::simd {

// The instruction sets the kernels are compiled for, best first.
enum class Isa { kAvx512, kAvx2, kBaseline };

// The best one this CPU runs. GAPS_CPU_SIMD=avx2 or =baseline lowers it (to test every variant).
inline Isa best_isa() {
  static const Isa isa = [] {
    Isa best = Isa::kBaseline;
#if defined(__x86_64__) || defined(__i386__)
    __builtin_cpu_init();
    if (__builtin_cpu_supports("avx2") && __builtin_cpu_supports("fma")) best = Isa::kAvx2;
    if (best == Isa::kAvx2 && __builtin_cpu_supports("avx512f") && __builtin_cpu_supports("avx512dq") &&
        __builtin_cpu_supports("avx512bw") && __builtin_cpu_supports("avx512vl"))
      best = Isa::kAvx512;
#endif
    const char* env = std::getenv("GAPS_CPU_SIMD");
    const std::string wanted = env ? env : "";
    if (wanted == "baseline") return Isa::kBaseline;
    if (wanted == "avx2" && best == Isa::kAvx512) return Isa::kAvx2;
    return best;
  }();
  return isa;
}

// Picks the copy of a kernel compiled for best_isa().
template <typename F>
F pick_for_isa(F avx512, F avx2, F baseline) {
  switch (best_isa()) {
    case Isa::kAvx512:
      return avx512;
    case Isa::kAvx2:
      return avx2;
    default:
      return baseline;
  }
}

}  // namespace gaps::simd

// Compiles the kernel header named by GAPS_SIMD_KERNELS once per instruction set (see simd.h):
//
//   #define GAPS_SIMD_KERNELS "gs_trainer/some_kernels_cpu.h"
//   #include "gs_trainer/raster/cpu/simd_multiversion.h"
//
// Inside the kernel header, GAPS_SIMD_NS names the copy's namespace (avx512, avx2, baseline) and
// GAPS_SIMD_BYTES the native vector width in bytes. No include guard: it is meant to be included once per
// kernel header. The including file must include every system header the kernels use beforehand, so
// that no library code is parsed under a target pragma.
#ifndef GAPS_SIMD_KERNELS
#error "define GAPS_SIMD_KERNELS before including simd_multiversion.h"
#endif

#if defined(__x86_64__) || defined(__i386__)
// Clang spells "compile the following functions for this target" differently from GCC.
#if defined(__clang__)
#pragma clang attribute push(__attribute__((target("avx512f,avx512dq,avx512bw,avx512vl,avx2,fma"))), \
                             apply_to = function)
#else
#pragma GCC push_options
#pragma GCC target("avx512f,avx512dq,avx512bw,avx512vl,avx2,fma")
#endif
#define GAPS_SIMD_NS avx512
#define GAPS_SIMD_BYTES 64
#include GAPS_SIMD_KERNELS
#undef GAPS_SIMD_NS
#undef GAPS_SIMD_BYTES
#if defined(__clang__)
#pragma clang attribute pop
#pragma clang attribute push(__attribute__((target("avx2,fma"))), apply_to = function)
#else
#pragma GCC pop_options
#pragma GCC push_options
#pragma GCC target("avx2,fma")
#endif
#define GAPS_SIMD_NS avx2
#define GAPS_SIMD_BYTES 32
#include GAPS_SIMD_KERNELS
#undef GAPS_SIMD_NS
#undef GAPS_SIMD_BYTES
#if defined(__clang__)
#pragma clang attribute pop
#else
#pragma GCC pop_options
#endif
#endif

#define GAPS_SIMD_NS baseline
#define GAPS_SIMD_BYTES 16
#include GAPS_SIMD_KERNELS
#undef GAPS_SIMD_NS
#undef GAPS_SIMD_BYTES

#if !(defined(__x86_64__) || defined(__i386__))
// Other architectures: the "avx512" and "avx2" copies are the baseline one.
#define GAPS_SIMD_NS avx512
#define GAPS_SIMD_BYTES 16
#include GAPS_SIMD_KERNELS
#undef GAPS_SIMD_NS
#undef GAPS_SIMD_BYTES
#define GAPS_SIMD_NS avx2
#define GAPS_SIMD_BYTES 16
#include GAPS_SIMD_KERNELS
#undef GAPS_SIMD_NS
#undef GAPS_SIMD_BYTES
#endif

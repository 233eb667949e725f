#pragma once
// How the tests in tests/gpu/ skip where they cannot run, so that `ctest -L gpu` on a machine without a
// CUDA device (CI) reports each of them as skipped, all for the same reason: "no CUDA device".
#include <ATen/ATen.h>
#include <gtest/gtest.h>

// LibTorch's CUDA operations on a device: enough for tests of ATen code and the pipelines.
#define GAPS_REQUIRE_CUDA()                               \
  do {                                                    \
    if (!at::hasCUDA()) GTEST_SKIP() << "no CUDA device"; \
  } while (false)

// The project's own kernels, compiled only where nvcc was found (GAPS_CUDA_KERNELS), and a device for them.
#if defined(GAPS_CUDA_KERNELS)
#define GAPS_REQUIRE_CUDA_KERNELS() GAPS_REQUIRE_CUDA()
#else
#define GAPS_REQUIRE_CUDA_KERNELS() GTEST_SKIP() << "built without the CUDA kernels"
#endif

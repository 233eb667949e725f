// NumPy .npy bytes (LLFF's poses_bounds.npy, cached depth maps) through parse_npy.
#include <ATen/ATen.h>
#include "common/npy.h"
#include "fuzz/fuzz_support.h"

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  const auto array = gaps::parse_npy(gaps::fuzz::as_bytes(data, size), "input.npy");
  if (!array.ok()) return 0;
  // What parsed must be what it claims: as many values as its shape holds.
  int64_t count = 1;
  for (int64_t d : array->shape) count *= d;
  if (array->data.numel() != count) __builtin_trap();
  return 0;
}

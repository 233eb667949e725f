#pragma once
// The element count of a shape that arrives from outside (a file header, a message), checked before any
// tensor is made: no negative extent, and the product of the extents, zero-sized ones counted as 1, within
// `limit`. A shape with a zero holds nothing, but LibTorch still multiplies its other extents into strides
// and throws when they overflow (found by fuzz/npy_fuzz.cpp and fuzz/generation_request_fuzz.cpp).
#include <algorithm>
#include <cstdint>
#include <vector>

#include "absl/status/statusor.h"

namespace gaps {

inline absl::StatusOr<int64_t> checked_element_count(const std::vector<int64_t>& shape, int64_t limit) {
  int64_t count = 1, strides = 1;
  for (int64_t extent : shape) {
    if (extent < 0) return absl::InvalidArgumentError("negative extent in the shape");
    if (std::max<int64_t>(extent, 1) > limit / strides) return absl::InvalidArgumentError("shape is too large");
    strides *= std::max<int64_t>(extent, 1);
    count *= extent;
  }
  return count;
}

}  // namespace gaps

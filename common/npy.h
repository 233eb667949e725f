#pragma once
// NumPy .npy files (format versions 1.0, 2.0 and 3.0): the simple numeric subset that scene formats use.
#include <cstdint>
#include <filesystem>
#include <string>
#include <vector>

#include <ATen/Tensor.h>
#include "absl/status/statusor.h"
#include "absl/strings/string_view.h"

namespace gaps {

struct NpyArray {
  std::vector<int64_t> shape;  // as stored; empty for a 0-d array
  std::string descr;           // the stored dtype, e.g. "<f8"
  // The values converted to float64 (C order, shaped like `shape`). 64-bit integers beyond 2^53 lose
  // precision, which is irrelevant for the poses, bounds and indices these files hold.
  at::Tensor data;
};

// Little-endian (or byte-order-free) bool/int/uint/float of 1..8 bytes, C order. Fortran order,
// big-endian and structured dtypes are rejected. Errors name `path`.
absl::StatusOr<NpyArray> read_npy(const std::filesystem::path& path);
// The same from bytes already in memory; `name` is what errors call the data.
absl::StatusOr<NpyArray> parse_npy(absl::string_view bytes, absl::string_view name);
// Writes a float32 or float64 tensor (any other dtype is stored as float64) as a version 1.0 file.
absl::Status write_npy(const std::filesystem::path& path, const at::Tensor& array);

}  // namespace gaps

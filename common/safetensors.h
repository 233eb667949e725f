#pragma once
// Memory-mapped reader of the safetensors format (8-byte little-endian header length, JSON header, raw
// data). Tensors view the mapping directly (no copy); the mapping lives as long as any of them.
#include <map>
#include <string>

#include <ATen/Tensor.h>
#include "absl/status/statusor.h"

namespace gaps::sdxl {

// name -> tensor, CPU, in the file's dtype (F32, F16, BF16, F64, I64, I32, I16, I8, U8, BOOL).
using TensorMap = std::map<std::string, at::Tensor>;

// Maps the file and validates its header: length within the file, JSON object, known dtypes, offsets in
// bounds, sizes matching shape x dtype, no overlapping tensors. Errors name the file and the tensor.
absl::StatusOr<TensorMap> read_safetensors(const std::string& path);

// The header's "__metadata__" (string -> string; empty when the file has none). Errors name the file.
using SafetensorsMetadata = std::map<std::string, std::string>;
absl::StatusOr<SafetensorsMetadata> read_safetensors_metadata(const std::string& path);

// The same format in memory (what one worker hands another, e.g. LoRA adapters): decode views `bytes`, kept
// alive as long as any tensor is; errors name `source` like a file's path.
struct DecodedSafetensors {
  TensorMap tensors;
  SafetensorsMetadata metadata;
};
absl::StatusOr<DecodedSafetensors> decode_safetensors(std::string bytes, const std::string& source);
absl::StatusOr<std::string> encode_safetensors(const TensorMap& tensors, const SafetensorsMetadata& metadata = {});

// Writes tensors (any supported dtype, made contiguous on the CPU) and optional "__metadata__" to path.
absl::Status write_safetensors(const std::string& path, const TensorMap& tensors,
                               const SafetensorsMetadata& metadata = {});

}  // namespace gaps::sdxl

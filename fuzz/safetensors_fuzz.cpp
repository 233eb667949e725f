// safetensors files (model weights) and the same format in memory (adapters one worker hands another): header and
// the tensors it maps.
#include <cstdlib>

#include <ATen/ATen.h>
#include "common/safetensors.h"
#include "fuzz/fuzz_support.h"

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  const std::string bytes(gaps::fuzz::as_bytes(data, size));
  const auto path = gaps::fuzz::write_scratch("input.safetensors", bytes).string();
  const auto metadata = gaps::sdxl::read_safetensors_metadata(path);
  const auto tensors = gaps::sdxl::read_safetensors(path);
  const auto decoded = gaps::sdxl::decode_safetensors(bytes, "fuzz input");
  // One parser behind both: the bytes decode exactly when the file's tensors and metadata read.
  if (decoded.ok() != (tensors.ok() && metadata.ok())) std::abort();
  // Every tensor views the file's mapping (or the bytes): reading all of it must stay inside.
  if (tensors.ok())
    for (const auto& [name, tensor] : *tensors) (void)tensor.clone();
  if (decoded.ok())
    for (const auto& [name, tensor] : decoded->tensors) (void)tensor.clone();
  return 0;
}

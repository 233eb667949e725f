// safetensors files (model weights): header and the tensors it maps.
#include <ATen/ATen.h>
#include "common/safetensors.h"
#include "fuzz/fuzz_support.h"

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  const auto path = gaps::fuzz::write_scratch("input.safetensors", gaps::fuzz::as_bytes(data, size)).string();
  (void)gaps::sdxl::read_safetensors_metadata(path);
  const auto tensors = gaps::sdxl::read_safetensors(path);
  if (!tensors.ok()) return 0;
  // Every tensor views the file's mapping: reading all its bytes must stay inside the file.
  for (const auto& [name, tensor] : *tensors) (void)tensor.clone();
  return 0;
}

// PyTorch checkpoints (zip archives or the legacy pickle stream) through the state-dict loader.
#include <ATen/ATen.h>
#include "common/torch_pickle.h"
#include "fuzz/fuzz_support.h"

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  const auto path = gaps::fuzz::write_scratch("input.pth", gaps::fuzz::as_bytes(data, size)).string();
  const auto tensors = gaps::load_torch_state_dict(path);
  if (!tensors.ok()) return 0;
  for (const auto& [name, tensor] : *tensors) (void)tensor.clone();
  return 0;
}

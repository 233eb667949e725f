#pragma once
// Reader for PyTorch checkpoint files (what torch.save writes), without Python.
//
// Both container formats are supported:
//  - zip (torch >= 1.6 default): <archive>/data.pkl plus one record <archive>/data/<key> per
//  storage;
//  - legacy (pre-zip, `_use_new_zipfile_serialization=False` or old files such as the LPIPS
//  weights):
//    magic-number, protocol and sys-info pickles, the main pickle, a pickle listing the storage
//    keys, then for each key an int64 element count followed by the raw little-endian storage
//    bytes.
// The main pickle is run on a small pickle VM that understands what state dicts are made of
// (dicts/OrderedDicts, tuples, lists, strings, numbers, None/bools, tensors rebuilt through
// torch._utils._rebuild_tensor_v2 from persistent-id storages). Any other callable is rejected, so
// loading never executes arbitrary code.
#include <ATen/Tensor.h>

#include <map>
#include <string>

#include "absl/status/statusor.h"

namespace gaps {

// Loads a flat {name: tensor} mapping (a module's state_dict). Tensors come back on the CPU,
// contiguous, with the dtype they were saved with; views (storage offsets, strides, shared
// storages) are materialised as independent copies. Errors name the file and what was wrong
// (truncation, an unsupported opcode or callable, a non-tensor entry, a tensor exceeding its
// storage, ...).
absl::StatusOr<std::map<std::string, at::Tensor>> load_torch_state_dict(const std::string& path);

}  // namespace gaps

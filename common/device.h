#pragma once
// Device names as the programs take them (--device cpu, cuda, cuda:N), checked before any work.
#include <string>

#include "absl/status/status.h"

namespace gaps {

// A usage error (common/error_kind.h) naming the device when `name` does not parse as cpu, cuda or cuda:N.
absl::Status check_device_name(const std::string& name);
// check_device_name, and a CUDA device must exist here (its index among those present).
absl::Status check_device(const std::string& name);

}  // namespace gaps

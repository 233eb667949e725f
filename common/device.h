#pragma once
// Device names as the programs take them (--device cpu, cuda, cuda:N), checked before any work.
#include <string>

#include "absl/status/status.h"

namespace gaps {

// A usage error (common/error_kind.h) naming the device when `name` does not parse as cpu, cuda or cuda:N.
absl::Status check_device_name(const std::string& name);
// check_device_name, and a CUDA device must exist here (its index among those present).
absl::Status check_device(const std::string& name);

// Caps what the CUDA caching allocator of this process may hold on `device` at `gib` GiB (0: no cap), so that
// processes sharing one card (a trainer and a diffusion worker on a 24 GB card) each stay within their share:
// an allocation past the cap fails with an out-of-memory error instead of starving the other process. The
// CUDA context and the libraries' own workspaces come on top (about 0.5 GiB per process). Usage errors for
// a cap on the CPU, a negative cap, or one larger than the device.
absl::Status limit_device_memory(const std::string& device, double gib);

}  // namespace gaps

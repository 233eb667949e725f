#include "common/device.h"

#include <optional>

#include <ATen/Context.h>
#include <c10/core/Device.h>
#include "absl/strings/str_cat.h"
#include "common/error_kind.h"

namespace gaps {
namespace {

// c10 throws on names it does not know; cpu and cuda are the devices the programs train and generate on.
std::optional<c10::Device> parse_device(const std::string& name) {
  try {
    const c10::Device device(name);
    if (device.is_cpu() || device.is_cuda()) return device;
  } catch (const std::exception&) {
  }
  return std::nullopt;
}

}  // namespace

absl::Status check_device_name(const std::string& name) {
  if (!parse_device(name)) return usage_error(absl::StrCat("device '", name, "' is not cpu, cuda or cuda:N"));
  return absl::OkStatus();
}

absl::Status check_device(const std::string& name) {
  const std::optional<c10::Device> device = parse_device(name);
  if (!device) return check_device_name(name);
  if (!device->is_cuda()) return absl::OkStatus();
  if (!at::hasCUDA())
    return usage_error(absl::StrCat("device ", name, ": no CUDA device is available here (use --device cpu)"));
  if (device->has_index() && device->index() >= at::getNumGPUs())
    return usage_error(absl::StrCat("device ", name, ": there are only ", at::getNumGPUs(), " CUDA devices"));
  return absl::OkStatus();
}

}  // namespace gaps

#include "common/device.h"

#include <cmath>
#include <optional>

#include <ATen/Context.h>
#include <ATen/ops/empty.h>
#include <c10/core/Device.h>
#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "common/error_kind.h"

#if defined(GAPS_CUDA_KERNELS)
#include <c10/cuda/CUDACachingAllocator.h>
#include <c10/cuda/CUDAFunctions.h>
#include <cuda_runtime_api.h>
#endif

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

absl::Status limit_device_memory(const std::string& device, double gib) {
  if (!(gib >= 0) || !std::isfinite(gib))
    return usage_error(absl::StrCat("GPU memory cap must be a number of GiB >= 0 (0: none), got ", gib));
  if (gib == 0) return absl::OkStatus();
  if (absl::Status st = check_device(device); !st.ok()) return st;
  const c10::Device d(device);
  if (!d.is_cuda()) return usage_error(absl::StrCat("a GPU memory cap needs a CUDA device, not ", device));
#if defined(GAPS_CUDA_KERNELS)
  const c10::DeviceIndex index = d.has_index() ? d.index() : c10::cuda::current_device();
  cudaDeviceProp properties{};
  if (cudaGetDeviceProperties(&properties, index) != cudaSuccess)
    return absl::InternalError(absl::StrCat("device ", device, ": cannot read its properties"));
  const double total_gib = static_cast<double>(properties.totalGlobalMem) / (1ull << 30);
  if (gib > total_gib)
    return usage_error(
        absl::StrFormat("GPU memory cap %.2f GiB is more than %s has (%.2f GiB)", gib, device, total_gib));
  // The allocator of a device exists once the device has been used: a first small allocation makes it.
  (void)at::empty({1}, at::TensorOptions().device(c10::Device(c10::DeviceType::CUDA, index)));
  c10::cuda::CUDACachingAllocator::setMemoryFraction(gib / total_gib, index);
  return absl::OkStatus();
#else
  return usage_error("a GPU memory cap needs a build with CUDA kernels (GAPS_CUDA=ON)");
#endif
}

}  // namespace gaps

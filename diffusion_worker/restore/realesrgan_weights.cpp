#include "diffusion_worker/restore/realesrgan_weights.h"

#include <system_error>
#include <utility>

#include <ATen/ATen.h>
#include "absl/status/status.h"
#include "absl/strings/str_cat.h"
#include "common/cache_dir.h"
#include "common/safetensors.h"
#include "common/status_macros.h"
#include "diffusion_worker/sdxl/weights.h"

namespace gaps::restore {

std::filesystem::path default_realesrgan_weights_path() {
  const std::filesystem::path cache = gaps_cache_dir();
  return cache.empty() ? cache : cache / "realesrgan" / "realesrgan-x4plus.safetensors";
}

absl::StatusOr<RrdbNet> load_rrdbnet(const std::filesystem::path& path, const RrdbNetConfig& config,
                                     at::ScalarType dtype, at::Device device) {
  std::error_code ec;
  if (path.empty() || !std::filesystem::is_regular_file(path, ec)) {
    return absl::NotFoundError(absl::StrCat("Real-ESRGAN weights not found at '", path.string(), "': run `",
                                            kRealEsrganSetupCommand,
                                            "` (it downloads and converts them, scripts/realesrgan_weights.py)"));
  }
  GAPS_ASSIGN_OR_RETURN(sdxl::TensorMap tensors, sdxl::read_safetensors(path.string()));
  sdxl::WeightLoader loader(path.string(), std::move(tensors), at::TensorOptions().dtype(dtype).device(device));
  RrdbNet net = RrdbNet::load(loader, config);
  GAPS_RETURN_IF_ERROR(loader.finish());
  return net;
}

}  // namespace gaps::restore

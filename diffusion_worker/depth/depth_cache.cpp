#include "diffusion_worker/depth/depth_cache.h"

#include <filesystem>
#include <system_error>

#include <ATen/ATen.h>
#include "absl/strings/ascii.h"
#include "absl/strings/str_cat.h"
#include "common/npy.h"
#include "common/status_macros.h"

namespace gaps::depth {
namespace {

namespace fs = std::filesystem;

absl::Status check_key_part(const std::string& what, const std::string& name) {
  bool plain = !name.empty() && name != "." && name != "..";
  for (const char ch : name) {
    plain = plain && (absl::ascii_isalnum(static_cast<unsigned char>(ch)) || ch == '.' || ch == '-' || ch == '_');
  }
  if (plain) return absl::OkStatus();
  return absl::InvalidArgumentError(absl::StrCat("depth cache: ", what, " id '", name,
                                                 "' must be letters, digits, '.', '-' or '_' (it names a file)"));
}

bool has_size(const at::Tensor& map, int64_t height, int64_t width) {
  return map.dim() == 2 && map.size(0) == height && map.size(1) == width;
}

// Written beside the target and renamed over it, so a reader never sees half a file.
absl::Status store(const fs::path& path, const at::Tensor& map) {
  std::error_code ec;
  fs::create_directories(path.parent_path(), ec);
  if (ec)
    return absl::InternalError(
        absl::StrCat("depth cache: cannot create ", path.parent_path().string(), ": ", ec.message()));
  const fs::path partial = fs::path(path).concat(".partial");
  GAPS_RETURN_IF_ERROR(write_npy(partial, map));
  fs::rename(partial, path, ec);
  if (ec) return absl::InternalError(absl::StrCat("depth cache: cannot write ", path.string(), ": ", ec.message()));
  return absl::OkStatus();
}

}  // namespace

absl::StatusOr<std::optional<at::Tensor>> DepthCache::read_stored(const std::string& path, int64_t height,
                                                                  int64_t width) {
  std::error_code ec;
  if (!fs::exists(path, ec)) return std::optional<at::Tensor>();
  GAPS_ASSIGN_OR_RETURN(NpyArray array, read_npy(path));
  if (!has_size(array.data, height, width)) return std::optional<at::Tensor>();  // stale: recomputed
  ++disk_reads_;
  return std::optional<at::Tensor>(array.data.to(at::kFloat));
}

absl::StatusOr<at::Tensor> DepthCache::get_or_compute(const std::string& scene, const std::string& view, int64_t height,
                                                      int64_t width, const Compute& compute) {
  GAPS_RETURN_IF_ERROR(check_key_part("scene", scene));
  GAPS_RETURN_IF_ERROR(check_key_part("view", view));
  std::lock_guard<std::mutex> lock(mutex_);
  const auto key = std::make_pair(scene, view);
  const auto it = maps_.find(key);
  if (it != maps_.end() && has_size(it->second, height, width)) return it->second;

  const std::string path = folder_.empty() ? "" : (fs::path(folder_) / scene / (view + ".npy")).string();
  if (!path.empty()) {
    GAPS_ASSIGN_OR_RETURN(std::optional<at::Tensor> stored, read_stored(path, height, width));
    if (stored) return maps_[key] = *stored;
  }
  GAPS_ASSIGN_OR_RETURN(at::Tensor map, compute());
  ++computed_;
  if (!map.defined() || !has_size(map, height, width)) {
    return absl::InternalError(
        absl::StrCat("depth cache: the depth computed for ", scene, "/", view, " is not ", height, " x ", width));
  }
  map = map.to(at::kCPU, at::kFloat).contiguous();
  if (!path.empty()) GAPS_RETURN_IF_ERROR(store(path, map));
  return maps_[key] = map;
}

void DepthCache::forget_scene(const std::string& scene) {
  std::lock_guard<std::mutex> lock(mutex_);
  for (auto it = maps_.begin(); it != maps_.end();) {
    it = it->first.first == scene ? maps_.erase(it) : std::next(it);
  }
}

}  // namespace gaps::depth

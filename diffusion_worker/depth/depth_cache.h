#pragma once
// Depth maps of ground-truth views, computed once per scene and reused across phases: in memory, and
// optionally in a folder (<folder>/<scene>/<view>.npy, float32) so a restarted worker need not recompute
// them. One folder belongs to one depth model: maps from another model would be taken as they are.
#include <cstdint>
#include <functional>
#include <map>
#include <mutex>
#include <optional>
#include <string>
#include <utility>

#include <ATen/Tensor.h>
#include "absl/status/statusor.h"

namespace gaps::depth {

class DepthCache {
 public:
  // folder empty: memory only.
  explicit DepthCache(std::string folder = "") : folder_(std::move(folder)) {}

  using Compute = std::function<absl::StatusOr<at::Tensor>()>;

  // The H x W depth of (scene, view): from memory, else from the folder, else compute() (whose result is
  // kept in memory and written to the folder). A stored map of another size than height x width is stale
  // (the view's image changed size) and is recomputed. scene and view become file names: non-empty,
  // letters, digits, '.', '-', '_' only, and not "." or "..". The returned tensor is the cached one
  // (CPU float32): read it, do not modify it in place.
  absl::StatusOr<at::Tensor> get_or_compute(const std::string& scene, const std::string& view, int64_t height,
                                            int64_t width, const Compute& compute);

  // Drops the scene's maps from memory (the folder keeps them).
  void forget_scene(const std::string& scene);

  int64_t computed() const { return computed_; }      // compute() calls so far
  int64_t disk_reads() const { return disk_reads_; }  // maps read from the folder so far
  const std::string& folder() const { return folder_; }

 private:
  // The stored map, or nullopt when there is none or it is stale; an unreadable file is an error.
  absl::StatusOr<std::optional<at::Tensor>> read_stored(const std::string& path, int64_t height, int64_t width);

  std::string folder_;
  std::mutex mutex_;
  std::map<std::pair<std::string, std::string>, at::Tensor> maps_;
  int64_t computed_ = 0, disk_reads_ = 0;
};

}  // namespace gaps::depth

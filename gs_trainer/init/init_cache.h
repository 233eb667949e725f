// The initialisation cache's files: one entry is a point-cloud PLY and, beside it, a JSON file with the
// method that made the points and its messages. Concurrent runs of one scene (a benchmark matrix, replicas
// sharing a data folder) read and fill the same entries at once.
#pragma once

#include <filesystem>
#include <optional>

#include "absl/status/statusor.h"
#include "common/ply.h"
#include "gs_trainer/init/initializer.h"

namespace gaps {

// The entry at `ply`, or nullopt when there is none or it cannot be read (the caller then recomputes it).
std::optional<InitResult> read_init_cache(const std::filesystem::path& ply);

// Stores `r` at `ply` and returns the points as read back, so that a first run and a cached run start from
// identical points. A concurrent reader sees the previous entry or this one, never part of one.
absl::StatusOr<PointCloud> write_init_cache(const std::filesystem::path& ply, const InitResult& r);

}  // namespace gaps

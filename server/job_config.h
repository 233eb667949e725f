#pragma once
// gaps.v1.TrainConfig -> the pipeline's RunOptions. Unset hyperparameters keep the library defaults (the
// paper's); the proto fields carry the names of TrainConfig / GapsConfig fields, so the mapping goes
// through their JSON form and cannot drift from the structs. Invalid values are INVALID_ARGUMENT.
#include <filesystem>

#include "absl/status/statusor.h"
#include "gaps/v1/trainer.pb.h"
#include "gs_trainer/pipeline.h"

namespace gaps {

// Fills everything but the scene/output folders, device, caches and generator. `has_points`: whether the
// upload carried an initial point cloud (needed by init "points").
absl::StatusOr<RunOptions> run_options_from_proto(const v1::TrainConfig& config, bool has_points,
                                                  const std::filesystem::path& points_file);

}  // namespace gaps

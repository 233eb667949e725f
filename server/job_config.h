#pragma once
// gaps.v1.TrainConfig -> the pipeline's RunOptions. Unset hyperparameters keep the library defaults (the
// paper's); the proto fields carry the names of TrainConfig / GapsConfig fields, so the mapping goes
// through their JSON form and cannot drift from the structs. Invalid values are INVALID_ARGUMENT.
#include <filesystem>
#include <string>

#include "absl/status/statusor.h"
#include "gaps/v1/trainer.pb.h"
#include "gs_trainer/pipeline.h"

namespace gaps {

// Fills everything but the scene/output folders, caches and generator. `has_points`: whether the upload
// carried an initial point cloud (needed by init "points"). The run trains on `trainer_device`; a job that
// names a device of another type (cpu on a CUDA trainer) is refused. An empty `trainer_device` checks the
// configuration only, leaving the job's device as it is.
absl::StatusOr<RunOptions> run_options_from_proto(const v1::TrainConfig& config, bool has_points,
                                                  const std::filesystem::path& points_file,
                                                  const std::string& trainer_device);

}  // namespace gaps

#pragma once
// A whole run: load a scene, split it by the protocol, initialise, train, evaluate on the test views and
// write the outputs (PLY, renders, metrics.json). `gaps train` and the end-to-end tests call this; its parts
// are in gs_trainer/run/.
#include <functional>
#include <string>

#include "absl/status/statusor.h"
#include "gs_trainer/run/mvs_settings.h"
#include "gs_trainer/run/options.h"
#include "gs_trainer/run/outputs.h"

namespace gaps {

// The cheap checks of a run, made before anything expensive (images, initialisation, a generator's weights):
// run_pipeline starts with them (and with common/device.h's check_device), and the command line calls them
// before loading a generator. The initialisation method is known (with its point cloud file), the resolutions
// are valid, the scene folder holds a scene (input data errors otherwise, common/error_kind.h) and has enough
// images for the views asked for (a usage error).
absl::Status check_scene(const RunOptions& options);

// A run stopped by divergence (non-finite loss or parameters) returns an Aborted status (is_divergence())
// and still writes metrics.json, with "status": "diverged", the error and the curve up to then.
absl::StatusOr<RunResult> run_pipeline(const RunOptions& options, const ProgressCallback& on_progress,
                                       const std::function<void(const std::string&)>& log);

// `gaps init`: the initial point cloud of a run's training views, written to out_dir as points.ply and as a
// COLMAP text model (sparse/0/{cameras,images,points3D}.txt) that COLMAP users can inspect or replace; when
// "mvs" made the points, also its depth and normal maps and fused cloud as a COLMAP dense workspace in
// out_dir/dense (init/colmap_dense.h).
absl::Status run_init_only(const RunOptions& options, const std::function<void(const std::string&)>& log);

}  // namespace gaps

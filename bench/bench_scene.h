#pragma once
// The scene side shared by the benchmarks that run on the benchmark protocol's training views.
#include <string>
#include <vector>

#include "absl/status/statusor.h"
#include "common/status_macros.h"
#include "gs_trainer/scene/scene.h"

namespace gaps::bench {

// The training cameras of the protocol's split (scene.h benchmark_split) of the scene in `folder`, loaded at
// -r `resolution`.
inline absl::StatusOr<std::vector<Camera>> training_cameras(const std::string& folder, int resolution, int views) {
  SceneLoadOptions load;
  load.resolution = resolution;
  GAPS_ASSIGN_OR_RETURN(const Scene scene, load_scene(folder, load));
  GAPS_ASSIGN_OR_RETURN(const Split split, benchmark_split(static_cast<int>(scene.cameras.size()), views));
  std::vector<Camera> cameras;
  for (int i : split.train) cameras.push_back(scene.cameras[i]);
  return cameras;
}

}  // namespace gaps::bench

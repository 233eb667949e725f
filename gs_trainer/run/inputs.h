#pragma once
// What a run starts from: the scene at a downscale factor, split by the benchmark protocol, the images of its
// views, the LPIPS network it measures with, and its options with "auto"'s Gaussian budget applied.
#include <optional>
#include <string>
#include <vector>

#include <ATen/Device.h>
#include "absl/status/statusor.h"
#include "gs_trainer/eval/lpips.h"
#include "gs_trainer/run/options.h"
#include "gs_trainer/scene/scene.h"
#include "gs_trainer/train/trainer.h"

namespace gaps {

// The scene of o.scene_dir at downscale factor `resolution`; what keeps it from loading is an input data error.
absl::StatusOr<Scene> load_scene_at(const RunOptions& o, int resolution);

// The protocol's split of the scene for `views` training views; asking for more views than there are is a usage
// error that says how many there are.
absl::StatusOr<Split> protocol_split(const Scene& scene, int views);

// The images of scene.cameras[indices], on `device`.
absl::StatusOr<std::vector<TrainingView>> load_views(const Scene& scene, const std::vector<int>& indices,
                                                     const at::Device& device);

std::vector<Camera> cameras_of(const std::vector<TrainingView>& views);

// What run_init_only and run_pipeline both start from: the scene split by the protocol (its description
// logged) and the training views loaded.
struct LoadedScene {
  Scene scene;
  Split split;
  std::string summary;
  std::vector<TrainingView> train;
};
absl::StatusOr<LoadedScene> load_scene_and_training_views(const RunOptions& o, const at::Device& device,
                                                          const RunLog& log);

// o with "auto"'s budget where it holds for these training views (with_auto_budget), said in the log.
RunOptions budgeted_options(const RunOptions& o, const std::vector<TrainingView>& train, const RunLog& log);

// The run's LPIPS network; nothing when the run measures without LPIPS (it is then reported as null).
absl::StatusOr<std::optional<Lpips>> run_lpips(const RunOptions& o, const at::Device& device);

}  // namespace gaps

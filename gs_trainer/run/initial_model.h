#pragma once
// The model a run trains from: its initial points by the method asked for (init/; "auto"'s larger views where
// they help), or a full 3DGS model given as --init-ply; and the record of what made it.
#include <filesystem>
#include <string>
#include <vector>

#include "absl/status/statusor.h"
#include "common/point_cloud.h"
#include "gs_trainer/model/gaussians.h"
#include "gs_trainer/run/options.h"
#include "gs_trainer/scene/scene.h"
#include "gs_trainer/train/trainer.h"

namespace gaps {

// What made a run's initial points: the method (RunOptions::init with "auto" resolved, fallbacks taken), the
// downscale factor of the views it read and its settings as used ("auto"'s larger views applied); then what it
// gave and cost in this process (a resumed run initialises again, usually from the cache).
struct InitRecord {
  std::string method;
  double resolution = 0;  // 0.5: a service job's larger views (RunOptions::larger_views_dir)
  PatchMatchOptions patchmatch;
  FusionOptions fusion;
  SparseOptions sparse;
  int64_t points = 0;       // the initial Gaussians
  double seconds = 0.0;     // wall clock from reading the views for it to the initial model
  bool from_cache = false;  // the points were read from the init cache, not computed
};

// The initial point cloud of the training views `train`. *record (if given): what made the points.
// dense_workspace: InitOptions::dense_workspace.
absl::StatusOr<PointCloud> initial_points(const RunOptions& o, const Scene& scene,
                                          const std::vector<TrainingView>& train, const RunLog& log,
                                          InitRecord* record = nullptr,
                                          const std::filesystem::path& dense_workspace = {});

// The model training starts from: the Gaussians of a full 3DGS PLY given as --init-ply (every property, so
// that training continues it; its SH brought to the run's degree), or Gaussians made from initial_points.
// *record as in initial_points (method "ply-model" for a full model), with the count and the wall-clock seconds.
absl::StatusOr<GaussianModel> initial_model(const RunOptions& o, const Scene& scene,
                                            const std::vector<TrainingView>& train, const RunLog& log,
                                            InitRecord* record);

}  // namespace gaps

#include "gs_trainer/run/inputs.h"

#include "absl/strings/str_cat.h"
#include "common/error_kind.h"
#include "common/status_macros.h"

namespace gaps {

absl::StatusOr<Scene> load_scene_at(const RunOptions& o, int resolution) {
  SceneLoadOptions load;
  load.resolution = resolution;
  absl::StatusOr<Scene> scene = load_scene(o.scene_dir, load);
  if (!scene.ok()) return input_data_error(scene.status());
  return scene;
}

absl::StatusOr<Split> protocol_split(const Scene& scene, int views) {
  const int images = static_cast<int>(scene.cameras.size());
  absl::StatusOr<Split> split = benchmark_split(images, views);
  if (split.ok()) return split;
  constexpr int kHold = 8;  // benchmark_split's: every 8th image is a test view
  const int test = (images + kHold - 1) / kHold;
  const int available = images - test;
  if (views <= available || available <= 0) return input_data_error(split.status());
  return usage_error(absl::StrCat(views, " training views asked for, but ", scene.root.string(), " has ", available,
                                  " besides its ", test, " test views (", images, " images, every ", kHold,
                                  "th held out): ask for at most ", available, " (0: all)"));
}

absl::StatusOr<std::vector<TrainingView>> load_views(const Scene& scene, const std::vector<int>& indices,
                                                     const at::Device& device) {
  std::vector<TrainingView> views;
  for (int i : indices) {
    absl::StatusOr<at::Tensor> image = load_camera_image(scene.cameras[i]);
    if (!image.ok()) return input_data_error(image.status());
    views.push_back({scene.cameras[i], image->to(device)});
  }
  return views;
}

std::vector<Camera> cameras_of(const std::vector<TrainingView>& views) {
  std::vector<Camera> cameras;
  for (const auto& v : views) cameras.push_back(v.camera);
  return cameras;
}

absl::StatusOr<LoadedScene> load_scene_and_training_views(const RunOptions& o, const at::Device& device,
                                                          const RunLog& log) {
  LoadedScene loaded;
  GAPS_ASSIGN_OR_RETURN(loaded.scene, load_scene_at(o, o.resolution));
  GAPS_ASSIGN_OR_RETURN(loaded.split, protocol_split(loaded.scene, o.views));
  loaded.summary = describe(loaded.scene, loaded.split);
  log(loaded.summary);
  GAPS_ASSIGN_OR_RETURN(loaded.train, load_views(loaded.scene, loaded.split.train, device));
  return loaded;
}

RunOptions budgeted_options(const RunOptions& o, const std::vector<TrainingView>& train, const RunLog& log) {
  RunOptions used = with_auto_budget(o, cameras_of(train));
  if (used.config.gaussians_per_variation == kAutoLargerViewsGaussiansPerVariation &&
      o.config.gaussians_per_variation < 0)
    log(absl::StrCat("budget: auto: the views face one way, so ", used.config.gaussians_per_variation,
                     " Gaussians per unit of their total variation (--gaussians-per-variation sets another)"));
  return used;
}

absl::StatusOr<std::optional<Lpips>> run_lpips(const RunOptions& o, const at::Device& device) {
  absl::StatusOr<std::optional<Lpips>> lpips = load_lpips(o.lpips_weights, o.lpips_backbone, device);
  if (!lpips.ok()) return input_data_error(lpips.status());
  return lpips;
}

}  // namespace gaps

#pragma once
// What the viewer shows of a run folder, a 3DGS PLY or a .splat file: the model (packed, pack.h, or the
// .splat bytes as they are) and the scene description of the page (scene.json): title, background, the
// training and test cameras (cameras.json), and every diffusion phase's pseudo-views at their poses with
// their admission decision and reason (phases.json; thumbnails from pseudo_views/ where saved).
#include <filesystem>
#include <string>
#include <utility>
#include <vector>

#include <nlohmann/json.hpp>
#include "absl/status/statusor.h"
#include "gs_trainer/scene/camera.h"

namespace gaps::viewer {

struct ViewerScene {
  std::string model_bytes;
  std::string model_format;  // "packed" or "splat"
  int64_t gaussians = 0;
  // scene.json less the model's URL: {title, background [3], model {format, count, sh_degree}, cameras [...],
  // phases [...], notes [...]}. Cameras as the page reads them: name, split, width, height, fx, fy, cx, cy,
  // R (world to camera, 9 values row-major) and t.
  nlohmann::json scene;
  // The pseudo-view images scene.json names: (URL path relative to the page, file).
  std::vector<std::pair<std::string, std::filesystem::path>> images;
};

nlohmann::json viewer_camera_json(const Camera& camera, const std::string& split);

// `input`: a run folder (point_cloud.ply, and when present cameras.json, phases.json, metrics.json,
// pseudo_views/), a .ply or a .splat file (with the cameras.json of its folder, if any). NotFound for a missing
// folder or file; a PLY or .splat that cannot be read is an InvalidArgument/DataLoss error naming the file.
absl::StatusOr<ViewerScene> load_viewer_scene(const std::filesystem::path& input);

}  // namespace gaps::viewer

// COLMAP scenes: a sparse model with registered images, the photos in images*/ under the scene root.
#include <algorithm>

#include <ATen/ATen.h>
#include "absl/strings/str_cat.h"
#include "common/status_macros.h"
#include "gs_trainer/scene/colmap.h"
#include "gs_trainer/scene/scene.h"
#include "gs_trainer/scene/scene_internal.h"

namespace gaps {
namespace {

namespace fs = std::filesystem;
using scene_internal::ImageFolder;

std::vector<const ColmapImage*> images_by_name(const ColmapModel& model) {
  std::vector<const ColmapImage*> images;
  for (const auto& [id, image] : model.images) images.push_back(&image);
  std::sort(images.begin(), images.end(), [](const ColmapImage* a, const ColmapImage* b) { return a->name < b->name; });
  return images;
}

// The files named in the model. LLFF's downscaled folders rename the photos (IMG_4026.JPG ->
// image000.png) but keep their order, so a folder with exactly one file per image maps by sorted position.
absl::StatusOr<std::vector<fs::path>> image_files(const std::vector<const ColmapImage*>& images, const fs::path& dir,
                                                  const fs::path& model_dir) {
  std::vector<fs::path> named;
  std::error_code ec;
  for (const ColmapImage* image : images) named.push_back(dir / image->name);
  const auto missing = std::find_if(named.begin(), named.end(), [&](const fs::path& p) { return !fs::exists(p, ec); });
  if (missing == named.end()) return named;
  absl::StatusOr<std::vector<fs::path>> listed = scene_internal::list_images(dir);
  if (listed.ok() && listed->size() == images.size()) return listed;
  return absl::NotFoundError(
      absl::StrCat(missing->string(), ": image file not found (registered in ", model_dir.string(), ")"));
}

std::optional<PointCloud> point_cloud(const std::vector<ColmapPoint>& points) {
  if (points.empty()) return std::nullopt;
  const int64_t n = static_cast<int64_t>(points.size());
  PointCloud cloud{at::empty({n, 3}, at::kFloat), at::empty({n, 3}, at::kFloat)};
  auto xyz = cloud.xyz.accessor<float, 2>();
  auto rgb = cloud.rgb.accessor<float, 2>();
  for (int64_t i = 0; i < n; ++i) {
    for (int c = 0; c < 3; ++c) {
      xyz[i][c] = static_cast<float>(points[i].xyz[c]);
      rgb[i][c] = points[i].rgb[c] / 255.0f;
    }
  }
  return cloud;
}

absl::StatusOr<Camera> full_camera(const ColmapModel& model, const ColmapImage& image, const fs::path& model_dir) {
  const auto found = model.cameras.find(image.camera_id);
  if (found == model.cameras.end())
    return absl::InvalidArgumentError(absl::StrCat(model_dir.string(), ": image ", image.name, " refers to camera ",
                                                   image.camera_id, ", which is not in the model"));
  absl::StatusOr<Camera> camera = colmap_to_camera(found->second, image);
  if (!camera.ok())
    return absl::Status(camera.status().code(), absl::StrCat(model_dir.string(), ": ", camera.status().message()));
  return camera;
}

}  // namespace

absl::StatusOr<Scene> load_colmap_scene(const fs::path& root, const SceneLoadOptions& options) {
  GAPS_RETURN_IF_ERROR(scene_internal::check_resolution(options));
  const std::optional<fs::path> model_dir = find_colmap_model(root);
  if (!model_dir)
    return absl::NotFoundError(
        absl::StrCat(root.string(), ": no COLMAP model (sparse/0/ or sparse/ with cameras and ", "images .bin/.txt)"));
  GAPS_ASSIGN_OR_RETURN(const ColmapModel model, read_colmap_model(*model_dir));
  if (model.images.empty())
    return absl::FailedPreconditionError(absl::StrCat(model_dir->string(), ": no registered images"));
  GAPS_ASSIGN_OR_RETURN(const ImageFolder folder, scene_internal::choose_image_folder(root, options));
  const std::vector<const ColmapImage*> images = images_by_name(model);
  GAPS_ASSIGN_OR_RETURN(const std::vector<fs::path> files, image_files(images, folder.dir, *model_dir));
  Scene scene{root, "colmap", {}, point_cloud(model.points)};
  for (size_t i = 0; i < images.size(); ++i) {
    GAPS_ASSIGN_OR_RETURN(Camera full, full_camera(model, *images[i], *model_dir));
    full.image_path = files[i];
    GAPS_ASSIGN_OR_RETURN(Camera camera, scene_internal::fit_to_image(full, folder.native, options.resolution));
    scene.cameras.push_back(std::move(camera));
  }
  return scene;
}

}  // namespace gaps

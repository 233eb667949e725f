#pragma once
// Pieces shared by the scene loaders (scene_*.cpp); not part of the public interface.
#include <filesystem>
#include <string>
#include <vector>

#include <Eigen/Core>
#include "absl/status/statusor.h"
#include "gs_trainer/scene/camera.h"
#include "gs_trainer/scene/scene.h"

namespace gaps::scene_internal {

// .png/.jpg/.jpeg in any letter case.
bool is_image_file(const std::filesystem::path& path);
// The image files directly inside `dir`, sorted by file name. Errors name `dir` when it is missing or empty.
absl::StatusOr<std::vector<std::filesystem::path>> list_images(const std::filesystem::path& dir);

// Where a scene's images come from for the requested resolution.
struct ImageFolder {
  std::filesystem::path dir;
  // True when the folder was made for this resolution (images_R, or images/ for R = 1): its image sizes
  // are the protocol's sizes. Otherwise images are resized on load to round(full / R).
  bool native = false;
};
// options.images_dir, else images_R (images/ for R = 1), else the folder images/ or images_*/ holding the
// largest images. Errors name the folder or the scene root.
absl::StatusOr<ImageFolder> choose_image_folder(const std::filesystem::path& root, const SceneLoadOptions& options);

// `full` carries the format's full-resolution intrinsics and its image_path. Returns it at the size the
// loaded scene uses: the file's own size when `native`, else round(full / resolution) (never upscaling a
// file that is smaller, which only R = 1 accepts). Reads the image header, so a missing or corrupt file
// fails here, naming it.
absl::StatusOr<Camera> fit_to_image(const Camera& full, bool native, int resolution);

// World-to-camera extrinsics from an OpenCV-convention camera-to-world rotation and centre.
void set_camera_to_world(const Eigen::Matrix3d& rotation_c2w, const Eigen::Vector3d& centre, Camera* camera);

// Python's round(): halves go to the even neighbour, so sizes match the reference implementations.
int round_half_even(double value);

absl::Status check_resolution(const SceneLoadOptions& options);

}  // namespace gaps::scene_internal

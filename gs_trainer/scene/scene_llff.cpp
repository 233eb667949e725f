// LLFF scenes (also Mip-NeRF 360): poses_bounds.npy, one row of 17 float64 per image in file-name order.
#include <cmath>

#include <ATen/ATen.h>
#include "absl/strings/str_cat.h"
#include "absl/strings/str_join.h"
#include "common/npy.h"
#include "common/status_macros.h"
#include "gs_trainer/scene/scene.h"
#include "gs_trainer/scene/scene_internal.h"

namespace gaps {
namespace {

namespace fs = std::filesystem;
using scene_internal::ImageFolder;

constexpr int kRowLength = 17;

absl::StatusOr<at::Tensor> read_poses(const fs::path& file) {
  GAPS_ASSIGN_OR_RETURN(NpyArray array, read_npy(file));
  if (array.shape.size() != 2 || array.shape[1] != kRowLength)
    return absl::InvalidArgumentError(
        absl::StrCat(file.string(), ": expected an N x 17 array, got shape (", absl::StrJoin(array.shape, ", "), ")"));
  return array.data;
}

// A row is a row-major 3x5 matrix [down | right | backwards | centre | (H, W, focal)] followed by near, far.
// The camera is defined at the full H x W size the file was made for.
absl::StatusOr<Camera> camera_from_row(const double* row, const std::string& where) {
  for (int k = 0; k < kRowLength; ++k) {
    if (!std::isfinite(row[k])) return absl::InvalidArgumentError(absl::StrCat(where, ": non-finite value"));
  }
  const auto column = [row](int c) { return Eigen::Vector3d(row[c], row[5 + c], row[10 + c]); };
  const Eigen::Vector3d hwf = column(4);
  if (hwf[0] < 1 || hwf[1] < 1 || hwf[2] <= 0)
    return absl::InvalidArgumentError(
        absl::StrCat(where, ": invalid H, W, focal (", hwf[0], ", ", hwf[1], ", ", hwf[2], ")"));
  // OpenCV axes: x = right (column 1), y = down (column 0), z = forward (minus column 2).
  Eigen::Matrix3d c2w;
  c2w << column(1), column(0), -column(2);
  GAPS_RETURN_IF_ERROR(check_rotation(c2w, where));
  Camera camera;
  scene_internal::set_camera_to_world(c2w, column(3), &camera);
  camera.height = static_cast<int>(std::lround(hwf[0]));
  camera.width = static_cast<int>(std::lround(hwf[1]));
  camera.fx = camera.fy = hwf[2];
  camera.cx = camera.width / 2.0;
  camera.cy = camera.height / 2.0;
  camera.near = row[15];
  camera.far = row[16];
  return camera;
}

absl::StatusOr<std::vector<fs::path>> matching_images(const fs::path& poses_file, int64_t rows, const fs::path& dir) {
  GAPS_ASSIGN_OR_RETURN(std::vector<fs::path> files, scene_internal::list_images(dir));
  if (static_cast<int64_t>(files.size()) != rows)
    return absl::FailedPreconditionError(absl::StrCat(poses_file.string(), " has ", rows, " poses but ", dir.string(),
                                                      " has ", files.size(), " images"));
  return files;
}

}  // namespace

absl::StatusOr<Scene> load_llff_scene(const fs::path& root, const SceneLoadOptions& options) {
  GAPS_RETURN_IF_ERROR(scene_internal::check_resolution(options));
  const fs::path poses_file = root / "poses_bounds.npy";
  GAPS_ASSIGN_OR_RETURN(const at::Tensor poses, read_poses(poses_file));
  GAPS_ASSIGN_OR_RETURN(const ImageFolder folder, scene_internal::choose_image_folder(root, options));
  GAPS_ASSIGN_OR_RETURN(const std::vector<fs::path> files, matching_images(poses_file, poses.size(0), folder.dir));
  Scene scene{root, "llff", {}, std::nullopt};
  const double* data = poses.data_ptr<double>();
  for (size_t i = 0; i < files.size(); ++i) {
    const std::string where = absl::StrCat(poses_file.string(), ": row ", i);
    GAPS_ASSIGN_OR_RETURN(Camera full, camera_from_row(data + i * kRowLength, where));
    full.name = files[i].filename().string();
    full.image_path = files[i];
    GAPS_ASSIGN_OR_RETURN(Camera camera, scene_internal::fit_to_image(full, folder.native, options.resolution));
    scene.cameras.push_back(std::move(camera));
  }
  return scene;
}

}  // namespace gaps

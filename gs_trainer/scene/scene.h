#pragma once
// Scenes on disk -> cameras (+ optional points), the benchmark split, and image loading.
// Formats: LLFF (poses_bounds.npy + images*/), COLMAP sparse models (sparse/0 or sparse/, .bin or .txt),
// nerfstudio / instant-ngp transforms.json.
#include <filesystem>
#include <optional>
#include <string>
#include <vector>

#include <ATen/Tensor.h>
#include "absl/status/statusor.h"
#include "common/point_cloud.h"
#include "gs_trainer/scene/camera.h"

namespace gaps {

struct Scene {
  std::filesystem::path root;
  std::string format;           // "llff", "colmap" or "transforms"
  std::vector<Camera> cameras;  // every image of the scene, sorted by file name, at the loaded resolution
  // Points shipped with the scene (COLMAP points3D). They were usually reconstructed from *all* images,
  // test views included, so the sparse-view protocol must not use them.
  std::optional<PointCloud> points;
};

struct SceneLoadOptions {
  // Downscale factor R: uses images_R/ when present (LLFF, Mip-NeRF 360), otherwise the full-size images
  // resized on load, with intrinsics scaled per axis to the rounded size.
  int resolution = 1;
  // Explicit image folder (relative to the scene root); overrides the choice above.
  std::string images_dir;
};

// A proper rotation up to rounding error; `where` prefixes the error ("file: row 3"). Also what the
// services check of cameras that arrive over the wire.
absl::Status check_rotation(const Eigen::Matrix3d& R, const std::string& where);
// Everything a camera must satisfy before training sees it: a proper rotation, a translation within
// kMaxCoordinate (common/point_cloud.h), positive finite focal lengths, a finite principal point, a size,
// and depth bounds that are finite, not negative and ordered (near <= far) when given. Every scene loader
// and the services' camera decoder call it.
absl::Status check_camera(const Camera& camera, const std::string& where);

// Picks the format: transforms.json, else a COLMAP model with registered images (sparse/0 or sparse/), else
// poses_bounds.npy. Errors name the directory (or the file at fault). Every camera passes check_camera and
// the scene's points check_point_cloud.
absl::StatusOr<Scene> load_scene(const std::filesystem::path& root, const SceneLoadOptions& options = {});
// One format explicitly. load_transforms_scene takes the scene folder or the .json file itself.
absl::StatusOr<Scene> load_llff_scene(const std::filesystem::path& root, const SceneLoadOptions& options = {});
absl::StatusOr<Scene> load_colmap_scene(const std::filesystem::path& root, const SceneLoadOptions& options = {});
absl::StatusOr<Scene> load_transforms_scene(const std::filesystem::path& path, const SceneLoadOptions& options = {});

// Pixels of one camera at its resolution, undistorted: HxWx3 float32 in [0, 1].
absl::StatusOr<at::Tensor> load_camera_image(const Camera& camera);

// The sparse-view benchmark split: test = every `hold`-th image (index % hold == 0); training = num_train
// views at round(linspace(0, M-1, num_train)) over the M remaining images. num_train <= 0 means all of them.
// Every run holds out every kTestViewHold-th image (LLFF's protocol), so evaluation needs no flag.
inline constexpr int kTestViewHold = 8;
struct Split {
  std::vector<int> train;
  std::vector<int> test;
};
absl::StatusOr<Split> benchmark_split(int num_images, int num_train, int hold = kTestViewHold);

// Multi-line human-readable summary (format, counts, resolution, intrinsics, split, bounds).
std::string describe(const Scene& scene, const Split& split);

}  // namespace gaps

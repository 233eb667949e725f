#include "gs_trainer/scene/scene.h"

#include <algorithm>
#include <cmath>

#include <ATen/ATen.h>
#include <opencv2/calib3d.hpp>
#include <opencv2/core.hpp>
#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "absl/strings/str_join.h"
#include "common/image_io.h"
#include "common/status_macros.h"
#include "gs_trainer/scene/colmap.h"
#include "gs_trainer/scene/scene_internal.h"

namespace gaps {
namespace {

namespace fs = std::filesystem;

// cv::undistort keeps the camera matrix, so the undistorted pixels fit the camera's pinhole intrinsics.
at::Tensor undistort(const at::Tensor& image, const Camera& camera) {
  const at::Tensor src = image.contiguous();
  const int height = static_cast<int>(src.size(0)), width = static_cast<int>(src.size(1));
  const cv::Mat in(height, width, CV_32FC3, src.data_ptr<float>());
  // OpenCV's pixel centres are integers, ours are at +0.5: shift the principal point by half a pixel.
  const cv::Matx33d K_cv(camera.fx, 0, camera.cx - 0.5, 0, camera.fy, camera.cy - 0.5, 0, 0, 1);
  at::Tensor dst = at::empty_like(src);
  cv::Mat out(height, width, CV_32FC3, dst.data_ptr<float>());
  cv::undistort(in, out, K_cv, camera.distortion);
  return dst;
}

// numpy's linspace: i * step + start, with the last value pinned to stop; then np.round (half to even).
std::vector<int> round_linspace(int stop, int num) {
  std::vector<int> values(num, 0);
  const double step = num > 1 ? static_cast<double>(stop) / (num - 1) : 0.0;
  for (int i = 0; i < num; ++i) values[i] = static_cast<int>(std::nearbyint(i * step));
  if (num > 1) values.back() = stop;
  return values;
}

std::string size_summary(const std::vector<Camera>& cameras) {
  const Camera& first = cameras.front();
  const bool same = std::all_of(cameras.begin(), cameras.end(),
                                [&](const Camera& c) { return c.width == first.width && c.height == first.height; });
  return absl::StrCat(same ? "" : "mixed sizes, first ", first.width, "x", first.height);
}

std::string bounds_summary(const std::vector<Camera>& cameras) {
  double near = cameras.front().near, far = cameras.front().far;
  for (const Camera& c : cameras) {
    near = std::min(near, c.near);
    far = std::max(far, c.far);
  }
  if (near == 0.0 && far == 0.0) return "  depth bounds: not given\n";
  return absl::StrFormat("  depth bounds: near %.4g, far %.4g\n", near, far);
}

std::string camera_summary(const Camera& c) {
  std::string line =
      absl::StrFormat("  first camera %s: fx %.3f fy %.3f cx %.3f cy %.3f", c.name, c.fx, c.fy, c.cx, c.cy);
  if (c.distortion.empty()) return line + ", no distortion\n";
  return absl::StrCat(line, ", distortion [", absl::StrJoin(c.distortion, ", "), "]\n");
}

}  // namespace

namespace {

// A folder of photos without poses: where to make a scene from them (COLMAP, into the layout load_colmap_scene
// reads). `photos` is the folder holding them: root/images, or root itself.
absl::Status photos_without_poses(const fs::path& root, const fs::path& photos) {
  const std::string images = (root / "images").string(), db = (root / "database.db").string();
  return absl::NotFoundError(absl::StrCat(
      root.string(),
      ": photos without camera poses. A scene is one of: transforms.json (nerfstudio, instant-ngp), a COLMAP model "
      "(sparse/0/ or sparse/, photos in images/), or LLFF's poses_bounds.npy (photos in images/). To make a COLMAP "
      "model from the photos",
      photos == root ? absl::StrCat(" (move them into ", images, "/ first)") : "", ":\n",
      "  colmap feature_extractor --database_path ", db, " --image_path ", images, "\n",
      "  colmap exhaustive_matcher --database_path ", db, "\n", "  mkdir -p ", (root / "sparse").string(),
      " && colmap mapper --database_path ", db, " --image_path ", images, " --output_path ",
      (root / "sparse").string()));
}

absl::StatusOr<Scene> checked(absl::StatusOr<Scene> scene) {
  if (!scene.ok()) return scene;
  for (const Camera& c : scene->cameras) GAPS_RETURN_IF_ERROR(check_camera(c, (scene->root / c.name).string()));
  if (scene->points) GAPS_RETURN_IF_ERROR(check_point_cloud(*scene->points, (scene->root / "points").string()));
  return scene;
}

}  // namespace

absl::StatusOr<Scene> load_scene(const fs::path& root, const SceneLoadOptions& options) {
  std::error_code ec;
  if (!fs::is_directory(root, ec)) return absl::NotFoundError(absl::StrCat(root.string(), ": scene folder not found"));
  if (fs::is_regular_file(root / "transforms.json", ec)) return checked(load_transforms_scene(root, options));
  if (find_colmap_model(root)) return checked(load_colmap_scene(root, options));
  if (fs::is_regular_file(root / "poses_bounds.npy", ec)) return checked(load_llff_scene(root, options));
  for (const fs::path& photos : {root / "images", root})
    if (scene_internal::list_images(photos).ok()) return photos_without_poses(root, photos);
  return absl::NotFoundError(absl::StrCat(root.string(),
                                          ": no scene found (expected transforms.json, a COLMAP model with images "
                                          "in sparse/0/ or sparse/, or poses_bounds.npy)"));
}

absl::StatusOr<at::Tensor> load_camera_image(const Camera& camera) {
  if (camera.width <= 0 || camera.height <= 0)
    return absl::InvalidArgumentError(absl::StrCat(camera.image_path.string(), ": camera has no valid size"));
  GAPS_ASSIGN_OR_RETURN(at::Tensor image, read_image(camera.image_path));
  const int width = static_cast<int>(image.size(1)), height = static_cast<int>(image.size(0));
  // Undistorting before resizing keeps the lens model at the resolution it describes.
  if (!camera.distortion.empty()) image = undistort(image, camera.resized(width, height));
  const bool resized = width != camera.width || height != camera.height;
  if (resized) image = resize_image(image, camera.width, camera.height);
  // An image changed here is kept as any stored image is, at 8 bits per channel: a service job receives it
  // as an 8-bit PNG, and the same flags must give the same views (and so the same initial cloud) either way.
  if (resized || !camera.distortion.empty()) image = image.clamp(0.0, 1.0).mul(255.0f).round().mul(1.0f / 255.0f);
  return image;
}

absl::StatusOr<Split> benchmark_split(int num_images, int num_train, int hold) {
  if (num_images < 1) return absl::InvalidArgumentError(absl::StrCat("num_images must be >= 1, got ", num_images));
  if (hold < 1) return absl::InvalidArgumentError(absl::StrCat("hold must be >= 1, got ", hold));
  Split split;
  std::vector<int> remaining;
  for (int i = 0; i < num_images; ++i) (i % hold == 0 ? split.test : remaining).push_back(i);
  const int m = static_cast<int>(remaining.size());
  if (m == 0)
    return absl::InvalidArgumentError(
        absl::StrCat("no training images: all ", num_images, " are test views (hold ", hold, ")"));
  const int n = num_train <= 0 ? m : num_train;
  if (n > m)
    return absl::InvalidArgumentError(
        absl::StrCat("num_train ", n, " exceeds the ", m, " non-test images of ", num_images, " (hold ", hold, ")"));
  for (int k : round_linspace(m - 1, n)) split.train.push_back(remaining[k]);
  return split;
}

std::string describe(const Scene& scene, const Split& split) {
  std::string out =
      absl::StrCat("scene ", scene.root.string(), " (", scene.format, "): ", scene.cameras.size(), " images");
  if (scene.cameras.empty()) return out + "\n";
  absl::StrAppend(&out, ", ", size_summary(scene.cameras), "\n");
  absl::StrAppend(&out, "  images from ", scene.cameras.front().image_path.parent_path().string(), "\n");
  out += camera_summary(scene.cameras.front());
  out += bounds_summary(scene.cameras);
  absl::StrAppend(&out, "  points: ", scene.points ? absl::StrCat(scene.points->xyz.size(0)) : "none", "\n");
  absl::StrAppend(&out, "  split: ", split.train.size(), " train [", absl::StrJoin(split.train, ", "), "], ",
                  split.test.size(), " test [", absl::StrJoin(split.test, ", "), "]\n");
  return out;
}

}  // namespace gaps

#include <algorithm>
#include <cctype>
#include <cmath>

#include "absl/strings/match.h"
#include "absl/strings/str_cat.h"
#include "common/image_io.h"
#include "common/status_macros.h"
#include "gs_trainer/scene/scene_internal.h"

namespace gaps::scene_internal {
namespace {

namespace fs = std::filesystem;

// Images whose aspect ratio differs from the camera's by more than this come from the wrong folder (or were
// rotated); per-axis intrinsics scaling would silently hide that.
constexpr double kAspectTolerance = 0.02;

bool is_image_folder_name(const std::string& name) { return name == "images" || absl::StartsWith(name, "images_"); }

// Pixel count of the first image of `dir`; 0 when it has none or its header is unreadable.
int64_t first_image_area(const fs::path& dir) {
  absl::StatusOr<std::vector<fs::path>> files = list_images(dir);
  if (!files.ok()) return 0;
  absl::StatusOr<std::pair<int, int>> size = read_image_size(files->front());
  return size.ok() ? int64_t{size->first} * size->second : 0;
}

absl::StatusOr<fs::path> largest_image_folder(const fs::path& root) {
  fs::path best;
  int64_t best_area = 0;
  std::error_code ec;
  for (const fs::directory_entry& entry : fs::directory_iterator(root, ec)) {
    if (!entry.is_directory(ec) || !is_image_folder_name(entry.path().filename().string())) continue;
    const int64_t area = first_image_area(entry.path());
    if (area > best_area) {
      best_area = area;
      best = entry.path();
    }
  }
  if (best.empty())
    return absl::NotFoundError(
        absl::StrCat(root.string(), ": no image folder (images/ or images_*/ with PNG/JPEG files)"));
  return best;
}

absl::Status check_aspect(const Camera& full, int width, int height) {
  const double expected = static_cast<double>(full.width) / full.height;
  const double actual = static_cast<double>(width) / height;
  if (std::abs(actual / expected - 1.0) <= kAspectTolerance) return absl::OkStatus();
  return absl::FailedPreconditionError(absl::StrCat(full.image_path.string(), ": image is ", width, "x", height,
                                                    " but the camera is ", full.width, "x", full.height,
                                                    " (aspect ratios differ)"));
}

}  // namespace

bool is_image_file(const fs::path& path) {
  std::string ext = path.extension().string();
  std::transform(ext.begin(), ext.end(), ext.begin(), [](unsigned char c) { return std::tolower(c); });
  return ext == ".png" || ext == ".jpg" || ext == ".jpeg";
}

absl::StatusOr<std::vector<fs::path>> list_images(const fs::path& dir) {
  std::error_code ec;
  if (!fs::is_directory(dir, ec)) return absl::NotFoundError(absl::StrCat(dir.string(), ": image folder not found"));
  std::vector<fs::path> files;
  for (const fs::directory_entry& entry : fs::directory_iterator(dir, ec)) {
    if (entry.is_regular_file(ec) && is_image_file(entry.path())) files.push_back(entry.path());
  }
  if (ec) return absl::PermissionDeniedError(absl::StrCat(dir.string(), ": cannot list folder: ", ec.message()));
  if (files.empty()) return absl::NotFoundError(absl::StrCat(dir.string(), ": no PNG/JPEG images in folder"));
  std::sort(files.begin(), files.end(),
            [](const fs::path& a, const fs::path& b) { return a.filename().string() < b.filename().string(); });
  return files;
}

absl::StatusOr<ImageFolder> choose_image_folder(const fs::path& root, const SceneLoadOptions& options) {
  std::error_code ec;
  if (!options.images_dir.empty()) {
    const fs::path dir = root / options.images_dir;
    if (!fs::is_directory(dir, ec)) return absl::NotFoundError(absl::StrCat(dir.string(), ": image folder not found"));
    return ImageFolder{dir, false};
  }
  const std::string name = options.resolution == 1 ? "images" : absl::StrCat("images_", options.resolution);
  if (fs::is_directory(root / name, ec)) return ImageFolder{root / name, true};
  GAPS_ASSIGN_OR_RETURN(fs::path largest, largest_image_folder(root));
  return ImageFolder{largest, false};
}

absl::StatusOr<Camera> fit_to_image(const Camera& full, bool native, int resolution) {
  if (full.width <= 0 || full.height <= 0)
    return absl::InvalidArgumentError(absl::StrCat(full.image_path.string(), ": camera has no valid size"));
  GAPS_ASSIGN_OR_RETURN(const auto size, read_image_size(full.image_path));
  const auto [width, height] = size;
  GAPS_RETURN_IF_ERROR(check_aspect(full, width, height));
  if (native) return full.resized(width, height);
  const int target_w = round_half_even(static_cast<double>(full.width) / resolution);
  const int target_h = round_half_even(static_cast<double>(full.height) / resolution);
  if (std::min(target_w, target_h) < 1) {
    // Said here, in the flag's words: the camera that would follow has a focal length of zero, and its
    // check would blame the focal length.
    return absl::InvalidArgumentError(absl::StrCat("resolution ", resolution, " would make the ", full.width, "x",
                                                   full.height, " images of ", full.image_path.parent_path().string(),
                                                   " ", target_w, "x", target_h, " pixels; the factor can be at most ",
                                                   std::min(full.width, full.height)));
  }
  if (width >= target_w && height >= target_h) return full.resized(target_w, target_h);
  // For R = 1 "full resolution" means the largest images the scene ships (bonsai has only 800x533).
  if (resolution == 1) return full.resized(width, height);
  return absl::FailedPreconditionError(absl::StrCat(full.image_path.string(), ": image is ", width, "x", height,
                                                    ", smaller than the ", target_w, "x", target_h, " that resolution ",
                                                    resolution, " needs"));
}

void set_camera_to_world(const Eigen::Matrix3d& rotation_c2w, const Eigen::Vector3d& centre, Camera* camera) {
  camera->R = rotation_c2w.transpose();
  camera->t = -camera->R * centre;
}

int round_half_even(double value) { return static_cast<int>(std::nearbyint(value)); }

absl::Status check_resolution(const SceneLoadOptions& options) {
  if (options.resolution >= 1) return absl::OkStatus();
  return absl::InvalidArgumentError(absl::StrCat("resolution must be >= 1, got ", options.resolution));
}

}  // namespace gaps::scene_internal

namespace gaps {

absl::Status check_rotation(const Eigen::Matrix3d& R, const std::string& where) {
  const double error = (R.transpose() * R - Eigen::Matrix3d::Identity()).cwiseAbs().maxCoeff();
  if (!(error < 1e-3)) return absl::InvalidArgumentError(absl::StrCat(where, ": rotation is not orthonormal"));
  if (R.determinant() < 0) return absl::InvalidArgumentError(absl::StrCat(where, ": rotation is a reflection"));
  return absl::OkStatus();
}

absl::Status check_camera(const Camera& c, const std::string& where) {
  GAPS_RETURN_IF_ERROR(check_rotation(c.R, where));
  const auto invalid = [&](const std::string& what) {
    return absl::InvalidArgumentError(absl::StrCat(where, ": ", what));
  };
  if (!c.t.allFinite() || c.t.cwiseAbs().maxCoeff() > kMaxCoordinate)
    return invalid(absl::StrCat("translation not finite or beyond +-", kMaxCoordinate));
  // A focal length of more than 1e7 pixels or a principal point that far out is no camera; it would only
  // overflow float32 projections.
  constexpr double kMaxPixels = 1e7;
  if (!(c.fx > 0 && c.fy > 0 && c.fx <= kMaxPixels && c.fy <= kMaxPixels))
    return invalid("focal lengths must be positive, finite and at most 1e7 pixels");
  if (!(std::abs(c.cx) <= kMaxPixels && std::abs(c.cy) <= kMaxPixels)) return invalid("principal point not finite");
  if (c.width <= 0 || c.height <= 0) return invalid("camera has no image size");
  if (!(c.near >= 0 && c.far >= 0 && c.far <= kMaxCoordinate))
    return invalid(absl::StrCat("depth bounds must be finite and not negative (near ", c.near, ", far ", c.far, ")"));
  if (c.far > 0 && c.near > c.far) return invalid(absl::StrCat("near bound ", c.near, " beyond far bound ", c.far));
  return absl::OkStatus();
}

}  // namespace gaps

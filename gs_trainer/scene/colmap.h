#pragma once
// COLMAP sparse models (cameras, images, points3D) in the binary and text formats, and their
// conversion to gaps cameras. COLMAP cameras use the OpenCV convention (x right, y down, z forward) and
// world-to-camera poses, with the pixel centre convention of camera.h.
#include <array>
#include <cstdint>
#include <filesystem>
#include <map>
#include <optional>
#include <string>
#include <vector>

#include <Eigen/Core>
#include "absl/status/statusor.h"
#include "gs_trainer/scene/camera.h"
#include "gs_trainer/scene/scene.h"

namespace gaps {

struct ColmapCamera {
  int id = 0;
  std::string model;  // "PINHOLE", "OPENCV", ...
  int64_t width = 0, height = 0;
  std::vector<double> params;  // in COLMAP's order for `model`
};

struct ColmapImage {
  int id = 0;
  Eigen::Vector4d qvec{1, 0, 0, 0};  // world-to-camera rotation (qw, qx, qy, qz)
  Eigen::Vector3d tvec = Eigen::Vector3d::Zero();
  int camera_id = 0;
  std::string name;  // path relative to the image folder
  std::vector<Eigen::Vector2d> xys;
  std::vector<int64_t> point3d_ids;  // one per xy, -1 when not triangulated
};

struct ColmapTrackElement {
  int image_id = 0;
  int point2d_idx = 0;
};

struct ColmapPoint {
  int64_t id = 0;
  Eigen::Vector3d xyz = Eigen::Vector3d::Zero();
  std::array<uint8_t, 3> rgb{0, 0, 0};
  double error = 0.0;
  std::vector<ColmapTrackElement> track;
};

struct ColmapModel {
  std::map<int, ColmapCamera> cameras;
  std::map<int, ColmapImage> images;
  std::vector<ColmapPoint> points;
};

// Parameter count of a COLMAP camera model, and the name of a numeric model id; nullopt when unknown.
std::optional<int> colmap_model_num_params(const std::string& model);
std::optional<std::string> colmap_model_name(int model_id);

// The folder (root/sparse/0, else root/sparse) holding cameras + images in .bin or .txt; nullopt if none.
std::optional<std::filesystem::path> find_colmap_model(const std::filesystem::path& root);

// Each part from `dir`, preferring .bin over .txt. A missing points3D gives an empty point list.
absl::StatusOr<std::map<int, ColmapCamera>> read_colmap_cameras(const std::filesystem::path& dir);
absl::StatusOr<ColmapModel> read_colmap_model(const std::filesystem::path& dir);

// Single files, by format. Errors name the file (and the record or line at fault).
absl::StatusOr<std::map<int, ColmapCamera>> read_colmap_cameras_bin(const std::filesystem::path& file);
absl::StatusOr<std::map<int, ColmapImage>> read_colmap_images_bin(const std::filesystem::path& file);
absl::StatusOr<std::vector<ColmapPoint>> read_colmap_points_bin(const std::filesystem::path& file);
absl::StatusOr<std::map<int, ColmapCamera>> read_colmap_cameras_txt(const std::filesystem::path& file);
absl::StatusOr<std::map<int, ColmapImage>> read_colmap_images_txt(const std::filesystem::path& file);
absl::StatusOr<std::vector<ColmapPoint>> read_colmap_points_txt(const std::filesystem::path& file);

// Writes cameras.txt, images.txt and points3D.txt into `dir` (created if needed), at full double precision.
absl::Status write_colmap_text(const std::filesystem::path& dir, const ColmapModel& model);

// COLMAP camera -> gaps intrinsics (full resolution) + distortion in OpenCV order. Supported models:
// SIMPLE_PINHOLE, PINHOLE, SIMPLE_RADIAL, RADIAL, OPENCV, FULL_OPENCV.
absl::StatusOr<Camera> colmap_to_camera(const ColmapCamera& camera, const ColmapImage& image);
// The reverse, e.g. to hand a gaps scene (or only its training views) to COLMAP-based tools: one PINHOLE
// (or OPENCV / FULL_OPENCV with distortion) camera per view, ids from 1 in the given order.
ColmapModel colmap_from_cameras(const std::vector<Camera>& cameras, const std::optional<PointCloud>& points);

Eigen::Matrix3d quaternion_to_rotation(const Eigen::Vector4d& qvec);  // (qw, qx, qy, qz), normalised first
Eigen::Vector4d rotation_to_quaternion(const Eigen::Matrix3d& R);     // qw >= 0

}  // namespace gaps

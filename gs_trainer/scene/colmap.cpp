#include "gs_trainer/scene/colmap.h"

#include <algorithm>
#include <cmath>

#include <ATen/ATen.h>
#include <Eigen/Geometry>
#include "absl/strings/str_cat.h"
#include "common/status_macros.h"

namespace gaps {
namespace {

namespace fs = std::filesystem;

struct ModelInfo {
  const char* name;
  int num_params;
};

// Indexed by COLMAP's numeric model id (colmap/sensor/models.h).
constexpr ModelInfo kModels[] = {
    {"SIMPLE_PINHOLE", 3},
    {"PINHOLE", 4},
    {"SIMPLE_RADIAL", 4},
    {"RADIAL", 5},
    {"OPENCV", 8},
    {"OPENCV_FISHEYE", 8},
    {"FULL_OPENCV", 12},
    {"FOV", 5},
    {"SIMPLE_RADIAL_FISHEYE", 4},
    {"RADIAL_FISHEYE", 5},
    {"THIN_PRISM_FISHEYE", 12},
    {"RAD_TAN_THIN_PRISM_FISHEYE", 16},
};

bool has_part(const fs::path& dir, const std::string& stem) {
  std::error_code ec;
  return fs::is_regular_file(dir / (stem + ".bin"), ec) || fs::is_regular_file(dir / (stem + ".txt"), ec);
}

// The .bin file when present, else the .txt one, else nullopt.
std::optional<fs::path> part_file(const fs::path& dir, const std::string& stem) {
  std::error_code ec;
  for (const char* ext : {".bin", ".txt"}) {
    if (fs::is_regular_file(dir / (stem + ext), ec)) return dir / (stem + ext);
  }
  return std::nullopt;
}

bool is_bin(const fs::path& file) { return file.extension() == ".bin"; }

// Intrinsics at full resolution and distortion in OpenCV order (k1, k2, p1, p2[, k3, k4, k5, k6]).
absl::Status fill_intrinsics(const ColmapCamera& cam, Camera* out) {
  const std::vector<double>& p = cam.params;
  const std::optional<int> expected = colmap_model_num_params(cam.model);
  if (expected && static_cast<int>(p.size()) != *expected)
    return absl::InvalidArgumentError(
        absl::StrCat("camera ", cam.id, " (", cam.model, ") has ", p.size(), " parameters, expected ", *expected));
  if (cam.model == "SIMPLE_PINHOLE" || cam.model == "SIMPLE_RADIAL" || cam.model == "RADIAL") {
    out->fx = out->fy = p[0];
    out->cx = p[1];
    out->cy = p[2];
    if (cam.model == "SIMPLE_RADIAL") out->distortion = {p[3], 0.0, 0.0, 0.0};
    if (cam.model == "RADIAL") out->distortion = {p[3], p[4], 0.0, 0.0};
    return absl::OkStatus();
  }
  if (cam.model == "PINHOLE" || cam.model == "OPENCV" || cam.model == "FULL_OPENCV") {
    out->fx = p[0];
    out->fy = p[1];
    out->cx = p[2];
    out->cy = p[3];
    out->distortion.assign(p.begin() + 4, p.end());
    return absl::OkStatus();
  }
  return absl::UnimplementedError(absl::StrCat("camera ", cam.id, ": unsupported camera model ", cam.model,
                                               " (supported: SIMPLE_PINHOLE, PINHOLE, SIMPLE_RADIAL, RADIAL, "
                                               "OPENCV, FULL_OPENCV)"));
}

// A distortion whose coefficients are all zero is an ideal pinhole; dropping it skips a no-op undistort.
void drop_zero_distortion(Camera* camera) {
  const auto& d = camera->distortion;
  if (std::all_of(d.begin(), d.end(), [](double v) { return v == 0.0; })) camera->distortion.clear();
}

ColmapCamera camera_model_for(const Camera& camera, int id) {
  ColmapCamera out{id, "PINHOLE", camera.width, camera.height, {camera.fx, camera.fy, camera.cx, camera.cy}};
  if (camera.distortion.empty()) return out;
  const size_t n = camera.distortion.size() <= 4 ? 4 : 8;
  out.model = n == 4 ? "OPENCV" : "FULL_OPENCV";
  std::vector<double> d = camera.distortion;
  d.resize(n, 0.0);
  out.params.insert(out.params.end(), d.begin(), d.end());
  return out;
}

std::vector<ColmapPoint> points_from_cloud(const PointCloud& cloud) {
  const at::Tensor xyz = cloud.xyz.to(at::kCPU, at::kDouble).contiguous();
  const at::Tensor rgb = cloud.rgb.to(at::kCPU, at::kFloat).clamp(0, 1).mul(255).round().to(at::kByte).contiguous();
  const auto x = xyz.accessor<double, 2>();
  const auto c = rgb.accessor<uint8_t, 2>();
  std::vector<ColmapPoint> points(xyz.size(0));
  for (int64_t i = 0; i < xyz.size(0); ++i) {
    points[i].id = i + 1;
    points[i].xyz = Eigen::Vector3d(x[i][0], x[i][1], x[i][2]);
    points[i].rgb = {c[i][0], c[i][1], c[i][2]};
  }
  return points;
}

}  // namespace

std::optional<int> colmap_model_num_params(const std::string& model) {
  for (const ModelInfo& info : kModels) {
    if (model == info.name) return info.num_params;
  }
  return std::nullopt;
}

std::optional<std::string> colmap_model_name(int model_id) {
  if (model_id < 0 || model_id >= static_cast<int>(std::size(kModels))) return std::nullopt;
  return std::string(kModels[model_id].name);
}

std::optional<fs::path> find_colmap_model(const fs::path& root) {
  for (const fs::path& dir : {root / "sparse" / "0", root / "sparse"}) {
    if (has_part(dir, "cameras") && has_part(dir, "images")) return dir;
  }
  return std::nullopt;
}

absl::StatusOr<std::map<int, ColmapCamera>> read_colmap_cameras(const fs::path& dir) {
  const std::optional<fs::path> file = part_file(dir, "cameras");
  if (!file) return absl::NotFoundError(absl::StrCat(dir.string(), ": no cameras.bin or cameras.txt"));
  return is_bin(*file) ? read_colmap_cameras_bin(*file) : read_colmap_cameras_txt(*file);
}

absl::StatusOr<ColmapModel> read_colmap_model(const fs::path& dir) {
  ColmapModel model;
  GAPS_ASSIGN_OR_RETURN(model.cameras, read_colmap_cameras(dir));
  const std::optional<fs::path> images = part_file(dir, "images");
  if (!images) return absl::NotFoundError(absl::StrCat(dir.string(), ": no images.bin or images.txt"));
  GAPS_ASSIGN_OR_RETURN(model.images,
                        is_bin(*images) ? read_colmap_images_bin(*images) : read_colmap_images_txt(*images));
  if (const std::optional<fs::path> points = part_file(dir, "points3D")) {
    GAPS_ASSIGN_OR_RETURN(model.points,
                          is_bin(*points) ? read_colmap_points_bin(*points) : read_colmap_points_txt(*points));
  }
  return model;
}

absl::StatusOr<Camera> colmap_to_camera(const ColmapCamera& camera, const ColmapImage& image) {
  Camera out;
  out.name = image.name;
  out.width = static_cast<int>(camera.width);
  out.height = static_cast<int>(camera.height);
  if (absl::Status s = fill_intrinsics(camera, &out); !s.ok()) return s;
  drop_zero_distortion(&out);
  out.R = quaternion_to_rotation(image.qvec);
  out.t = image.tvec;
  return out;
}

ColmapModel colmap_from_cameras(const std::vector<Camera>& cameras, const std::optional<PointCloud>& points) {
  ColmapModel model;
  for (size_t i = 0; i < cameras.size(); ++i) {
    const int id = static_cast<int>(i) + 1;
    model.cameras[id] = camera_model_for(cameras[i], id);
    ColmapImage image;
    image.id = id;
    image.camera_id = id;
    image.qvec = rotation_to_quaternion(cameras[i].R);
    image.tvec = cameras[i].t;
    image.name = cameras[i].name;
    model.images[id] = image;
  }
  if (points) model.points = points_from_cloud(*points);
  return model;
}

Eigen::Matrix3d quaternion_to_rotation(const Eigen::Vector4d& qvec) {
  return Eigen::Quaterniond(qvec[0], qvec[1], qvec[2], qvec[3]).normalized().toRotationMatrix();
}

Eigen::Vector4d rotation_to_quaternion(const Eigen::Matrix3d& R) {
  const Eigen::Quaterniond q(R);
  const Eigen::Vector4d v(q.w(), q.x(), q.y(), q.z());
  return q.w() < 0 ? Eigen::Vector4d(-v) : v;
}

}  // namespace gaps

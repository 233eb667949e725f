#include "gs_trainer/scene/cameras_json.h"

#include <cmath>

#include <nlohmann/json.hpp>
#include "absl/strings/str_cat.h"
#include "common/io_util.h"
#include "common/status_macros.h"
#include "gs_trainer/scene/scene.h"

namespace gaps {
namespace {

using nlohmann::json;

absl::StatusOr<double> number(const json& entry, const char* key, const std::string& where) {
  if (!entry.contains(key) || !entry[key].is_number())
    return absl::InvalidArgumentError(absl::StrCat(where, ": '", key, "' is missing or not a number"));
  const double value = entry[key].get<double>();
  if (!std::isfinite(value)) return absl::InvalidArgumentError(absl::StrCat(where, ": '", key, "' is not finite"));
  return value;
}

// `key` as `rows` x 3 numbers (rows == 1: a flat list of three).
absl::StatusOr<Eigen::MatrixXd> matrix(const json& entry, const char* key, int rows, const std::string& where) {
  const std::string shape = rows == 1 ? "a list of 3 numbers" : "3 rows of 3 numbers";
  const auto bad = [&] { return absl::InvalidArgumentError(absl::StrCat(where, ": '", key, "' must be ", shape)); };
  if (!entry.contains(key) || !entry[key].is_array() || entry[key].size() != (rows == 1 ? 3u : size_t(rows)))
    return bad();
  Eigen::MatrixXd m(rows, 3);
  for (int r = 0; r < rows; ++r) {
    const json& row = rows == 1 ? entry[key] : entry[key][r];
    if (!row.is_array() || row.size() != 3) return bad();
    for (int c = 0; c < 3; ++c) {
      if (!row[c].is_number() || !std::isfinite(row[c].get<double>())) return bad();
      m(r, c) = row[c].get<double>();
    }
  }
  return m;
}

std::string stem(const std::string& name) { return std::filesystem::path(name).stem().string(); }

}  // namespace

json camera_json(const Camera& camera, int id, const std::string& split) {
  const Eigen::Matrix3d c2w = camera.R.transpose();
  const Eigen::Vector3d position = camera.center();
  json rotation = json::array();
  for (int r = 0; r < 3; ++r) rotation.push_back({c2w(r, 0), c2w(r, 1), c2w(r, 2)});
  json entry = {{"id", id},
                {"img_name", stem(camera.name)},
                {"width", camera.width},
                {"height", camera.height},
                {"position", {position.x(), position.y(), position.z()}},
                {"rotation", rotation},
                {"fx", camera.fx},
                {"fy", camera.fy},
                {"cx", camera.cx},
                {"cy", camera.cy},
                {"image", camera.name}};
  if (!split.empty()) entry["split"] = split;
  return entry;
}

json cameras_json(const std::vector<CameraRecord>& cameras) {
  json list = json::array();
  for (size_t i = 0; i < cameras.size(); ++i)
    list.push_back(camera_json(cameras[i].camera, static_cast<int>(i), cameras[i].split));
  return list;
}

absl::StatusOr<CameraRecord> parse_camera_json(const json& entry, const std::string& where) {
  if (!entry.is_object()) return absl::InvalidArgumentError(absl::StrCat(where, ": not an object"));
  CameraRecord record;
  Camera& camera = record.camera;
  GAPS_ASSIGN_OR_RETURN(const double width, number(entry, "width", where));
  GAPS_ASSIGN_OR_RETURN(const double height, number(entry, "height", where));
  if (width < 1 || height < 1 || width > 1 << 16 || height > 1 << 16 || width != std::floor(width) ||
      height != std::floor(height))
    return absl::InvalidArgumentError(absl::StrCat(where, ": width and height must be whole numbers in [1, 65536]"));
  camera.width = static_cast<int>(width);
  camera.height = static_cast<int>(height);
  GAPS_ASSIGN_OR_RETURN(camera.fx, number(entry, "fx", where));
  GAPS_ASSIGN_OR_RETURN(camera.fy, number(entry, "fy", where));
  camera.cx = camera.width / 2.0;
  camera.cy = camera.height / 2.0;
  if (entry.contains("cx")) {
    GAPS_ASSIGN_OR_RETURN(camera.cx, number(entry, "cx", where));
  }
  if (entry.contains("cy")) {
    GAPS_ASSIGN_OR_RETURN(camera.cy, number(entry, "cy", where));
  }
  GAPS_ASSIGN_OR_RETURN(const Eigen::MatrixXd position, matrix(entry, "position", 1, where));
  GAPS_ASSIGN_OR_RETURN(const Eigen::MatrixXd c2w, matrix(entry, "rotation", 3, where));
  camera.R = c2w.transpose();
  camera.t = -camera.R * position.row(0).transpose();
  if (entry.contains("image") && entry["image"].is_string())
    camera.name = entry["image"].get<std::string>();
  else if (entry.contains("img_name") && entry["img_name"].is_string())
    camera.name = entry["img_name"].get<std::string>();
  if (entry.contains("split") && entry["split"].is_string()) record.split = entry["split"].get<std::string>();
  GAPS_RETURN_IF_ERROR(check_camera(camera, where));
  return record;
}

absl::StatusOr<std::vector<CameraRecord>> parse_cameras_json(const json& list, const std::string& where) {
  if (!list.is_array()) return absl::InvalidArgumentError(absl::StrCat(where, ": expected a list of cameras"));
  if (list.empty()) return absl::InvalidArgumentError(absl::StrCat(where, ": no cameras"));
  std::vector<CameraRecord> cameras;
  for (size_t i = 0; i < list.size(); ++i) {
    GAPS_ASSIGN_OR_RETURN(CameraRecord record, parse_camera_json(list[i], absl::StrCat(where, ": camera ", i)));
    cameras.push_back(std::move(record));
  }
  return cameras;
}

json transform_matrix_json(const Camera& camera) {
  Eigen::Matrix3d c2w = camera.R.transpose();
  c2w.col(1) *= -1.0;  // OpenCV -> OpenGL: y and z flipped
  c2w.col(2) *= -1.0;
  const Eigen::Vector3d centre = camera.center();
  json m = json::array();
  for (int r = 0; r < 3; ++r) m.push_back({c2w(r, 0), c2w(r, 1), c2w(r, 2), centre(r)});
  m.push_back({0.0, 0.0, 0.0, 1.0});
  return m;
}

absl::Status write_cameras_json(const std::filesystem::path& path, const std::vector<CameraRecord>& cameras) {
  return write_file_bytes(path, cameras_json(cameras).dump(1) + "\n");
}

absl::StatusOr<std::vector<CameraRecord>> read_cameras_json(const std::filesystem::path& path) {
  GAPS_ASSIGN_OR_RETURN(const std::string text, read_file_bytes(path, "cameras file"));
  const json list = json::parse(text, nullptr, /*allow_exceptions=*/false);
  if (list.is_discarded()) return absl::InvalidArgumentError(absl::StrCat(path.string(), ": not valid JSON"));
  return parse_cameras_json(list, path.string());
}

}  // namespace gaps

// nerfstudio / instant-ngp / NeRF-synthetic transforms.json: camera-to-world matrices in the OpenGL
// (Blender) convention, x right, y up, z backwards; intrinsics globally or per frame.
#include <algorithm>
#include <cmath>
#include <map>

#include <nlohmann/json.hpp>
#include "absl/strings/str_cat.h"
#include "common/image_io.h"
#include "common/io_util.h"
#include "common/status_macros.h"
#include "gs_trainer/scene/scene.h"
#include "gs_trainer/scene/scene_internal.h"

namespace gaps {
namespace {

namespace fs = std::filesystem;
using nlohmann::json;
using Params = std::map<std::string, double>;

// "near" and "far" (per frame or global) are gaps' own: the depth bounds of a scene that had them (LLFF's
// poses_bounds.npy) survive a round trip through transforms.json, as a submitted scene takes.
constexpr const char* kNumericKeys[] = {
    "fl_x", "fl_y", "cx", "cy", "w",    "h",  "camera_angle_x", "camera_angle_y", "k1",
    "k2",   "k3",   "p1", "p2", "near", "far"};

struct Frame {
  std::string file_path;
  Eigen::Matrix4d c2w;
  Params params;  // the global intrinsics, overridden by the frame's own
};

absl::Status read_params(const json& object, const std::string& where, Params* params) {
  for (const char* key : kNumericKeys) {
    if (!object.contains(key)) continue;
    if (!object[key].is_number())
      return absl::InvalidArgumentError(absl::StrCat(where, ": '", key, "' is not a number"));
    (*params)[key] = object[key].get<double>();
  }
  if (object.value("is_fisheye", false))
    return absl::UnimplementedError(absl::StrCat(where, ": fisheye cameras are not supported"));
  const std::string model = object.value("camera_model", std::string("OPENCV"));
  if (model != "OPENCV" && model != "PINHOLE" && model != "SIMPLE_PINHOLE")
    return absl::UnimplementedError(absl::StrCat(where, ": camera_model ", model, " is not supported"));
  return absl::OkStatus();
}

absl::StatusOr<Eigen::Matrix4d> read_matrix(const json& frame, const std::string& where) {
  const json* m = frame.contains("transform_matrix") ? &frame["transform_matrix"] : nullptr;
  if (m == nullptr || !m->is_array() || m->size() < 3)
    return absl::InvalidArgumentError(absl::StrCat(where, ": missing or malformed transform_matrix (4x4 expected)"));
  Eigen::Matrix4d c2w = Eigen::Matrix4d::Identity();
  for (int r = 0; r < static_cast<int>(m->size()) && r < 4; ++r) {
    const json& row = (*m)[r];
    if (!row.is_array() || row.size() != 4)
      return absl::InvalidArgumentError(absl::StrCat(where, ": transform_matrix row ", r, " needs 4 numbers"));
    for (int c = 0; c < 4; ++c) {
      if (!row[c].is_number() || !std::isfinite(row[c].get<double>()))
        return absl::InvalidArgumentError(
            absl::StrCat(where, ": transform_matrix has a non-finite or non-numeric entry"));
      c2w(r, c) = row[c].get<double>();
    }
  }
  return c2w;
}

absl::StatusOr<std::vector<Frame>> read_frames(const json& doc, const fs::path& file) {
  if (!doc.is_object() || !doc.contains("frames") || !doc["frames"].is_array() || doc["frames"].empty())
    return absl::InvalidArgumentError(absl::StrCat(file.string(), ": no 'frames' list"));
  Params global;
  GAPS_RETURN_IF_ERROR(read_params(doc, file.string(), &global));
  std::vector<Frame> frames;
  for (size_t i = 0; i < doc["frames"].size(); ++i) {
    const json& f = doc["frames"][i];
    const std::string where = absl::StrCat(file.string(), ": frame ", i);
    if (!f.is_object() || !f.contains("file_path") || !f["file_path"].is_string())
      return absl::InvalidArgumentError(absl::StrCat(where, ": missing 'file_path'"));
    Frame frame{f["file_path"].get<std::string>(), Eigen::Matrix4d::Identity(), global};
    GAPS_ASSIGN_OR_RETURN(frame.c2w, read_matrix(f, where));
    GAPS_RETURN_IF_ERROR(read_params(f, where, &frame.params));
    frames.push_back(std::move(frame));
  }
  std::stable_sort(frames.begin(), frames.end(),
                   [](const Frame& a, const Frame& b) { return a.file_path < b.file_path; });
  return frames;
}

// file_path is relative to the json and, in NeRF-synthetic style files, lacks the extension. It must stay
// inside the json's folder: a scene is a folder, and `gaps submit` uploads what the scene names, so a path
// leading elsewhere (absolute, or climbing out with "..") would send any readable file to the server.
absl::StatusOr<fs::path> resolve_image(const fs::path& base, const std::string& file_path, const std::string& where) {
  const fs::path relative = fs::path(file_path).lexically_normal();
  if (relative.is_absolute() || relative.empty() || *relative.begin() == "..")
    return absl::InvalidArgumentError(
        absl::StrCat(where, ": file_path '", file_path, "' leads outside the scene folder ", base.string()));
  const fs::path path = (base / relative).lexically_normal();
  std::error_code ec;
  if (fs::is_regular_file(path, ec)) return path;
  for (const char* ext : {".png", ".jpg", ".jpeg", ".PNG", ".JPG", ".JPEG"}) {
    fs::path with_ext = path;
    with_ext += ext;
    if (fs::is_regular_file(with_ext, ec)) return with_ext;
  }
  return absl::NotFoundError(absl::StrCat(path.string(), ": image file not found (", where, ")"));
}

struct ImageSource {
  fs::path file;
  bool native;  // as in scene_internal::ImageFolder
};

// nerfstudio keeps downscaled copies next to images/ as images_2/, images_4/, ... with the same names.
ImageSource pick_source(const fs::path& full, const fs::path& base, const SceneLoadOptions& options) {
  std::error_code ec;
  if (!options.images_dir.empty()) return {base / options.images_dir / full.filename(), false};
  if (options.resolution > 1 && full.parent_path().filename() == "images") {
    const fs::path scaled =
        full.parent_path().parent_path() / absl::StrCat("images_", options.resolution) / full.filename();
    if (fs::is_regular_file(scaled, ec)) return {scaled, true};
  }
  return {full, false};
}

absl::Status set_intrinsics(const Params& p, const std::string& where, Camera* camera) {
  const auto get = [&p](const char* key, double fallback) { return p.count(key) ? p.at(key) : fallback; };
  camera->width = static_cast<int>(std::lround(get("w", camera->width)));
  camera->height = static_cast<int>(std::lround(get("h", camera->height)));
  if (p.count("fl_x")) {
    camera->fx = p.at("fl_x");
    camera->fy = get("fl_y", camera->fx);
  } else if (p.count("camera_angle_x")) {
    camera->fx = 0.5 * camera->width / std::tan(0.5 * p.at("camera_angle_x"));
    camera->fy = p.count("camera_angle_y") ? 0.5 * camera->height / std::tan(0.5 * p.at("camera_angle_y")) : camera->fx;
  } else {
    return absl::InvalidArgumentError(absl::StrCat(where, ": no focal length (fl_x or camera_angle_x)"));
  }
  if (!(camera->fx > 0 && camera->fy > 0 && std::isfinite(camera->fx) && std::isfinite(camera->fy)))
    return absl::InvalidArgumentError(absl::StrCat(where, ": invalid focal length"));
  camera->cx = get("cx", camera->width / 2.0);
  camera->cy = get("cy", camera->height / 2.0);
  const std::vector<double> d = {get("k1", 0), get("k2", 0), get("p1", 0), get("p2", 0), get("k3", 0)};
  if (std::any_of(d.begin(), d.end(), [](double v) { return v != 0.0; })) camera->distortion = d;
  camera->near = get("near", 0.0);
  camera->far = get("far", 0.0);
  return absl::OkStatus();
}

absl::StatusOr<Camera> frame_camera(const Frame& frame, const fs::path& base, const std::string& where) {
  Camera camera;
  GAPS_ASSIGN_OR_RETURN(const fs::path full_path, resolve_image(base, frame.file_path, where));
  if (!frame.params.count("w") || !frame.params.count("h")) {
    GAPS_ASSIGN_OR_RETURN(const auto size, read_image_size(full_path));
    std::tie(camera.width, camera.height) = size;
  }
  GAPS_RETURN_IF_ERROR(set_intrinsics(frame.params, where, &camera));
  // OpenGL -> OpenCV: the camera's y and z axes flip.
  Eigen::Matrix3d c2w = frame.c2w.topLeftCorner<3, 3>();
  c2w.col(1) *= -1.0;
  c2w.col(2) *= -1.0;
  GAPS_RETURN_IF_ERROR(check_rotation(c2w, where));
  scene_internal::set_camera_to_world(c2w, frame.c2w.topRightCorner<3, 1>(), &camera);
  camera.name = full_path.filename().string();
  camera.image_path = full_path;
  return camera;
}

absl::StatusOr<json> parse_json(const fs::path& file) {
  GAPS_ASSIGN_OR_RETURN(const std::string text, read_file_bytes(file, "transforms file"));
  json doc = json::parse(text, nullptr, /*allow_exceptions=*/false);
  if (doc.is_discarded()) return absl::InvalidArgumentError(absl::StrCat(file.string(), ": invalid JSON"));
  return doc;
}

}  // namespace

absl::StatusOr<Scene> load_transforms_scene(const fs::path& path, const SceneLoadOptions& options) {
  GAPS_RETURN_IF_ERROR(scene_internal::check_resolution(options));
  std::error_code ec;
  const fs::path file = fs::is_directory(path, ec) ? path / "transforms.json" : path;
  const fs::path base = file.parent_path();
  GAPS_ASSIGN_OR_RETURN(const json doc, parse_json(file));
  GAPS_ASSIGN_OR_RETURN(const std::vector<Frame> frames, read_frames(doc, file));
  Scene scene{base, "transforms", {}, std::nullopt};
  for (size_t i = 0; i < frames.size(); ++i) {
    const std::string where = absl::StrCat(file.string(), ": frame ", frames[i].file_path);
    GAPS_ASSIGN_OR_RETURN(Camera full, frame_camera(frames[i], base, where));
    const ImageSource source = pick_source(full.image_path, base, options);
    full.image_path = source.file;
    GAPS_ASSIGN_OR_RETURN(Camera camera, scene_internal::fit_to_image(full, source.native, options.resolution));
    scene.cameras.push_back(std::move(camera));
  }
  return scene;
}

}  // namespace gaps

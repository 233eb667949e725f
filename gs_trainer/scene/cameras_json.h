#pragma once
// cameras.json in the layout of the 3DGS reference code (Inria), which its viewers and tools read: a list of
// {id, img_name, width, height, position, rotation, fx, fy} with `position` the camera centre and `rotation`
// the camera-to-world rotation (rows), OpenCV axes (x right, y down, z forward). gaps adds keys those tools
// ignore: cx, cy (Inria assumes the image centre), "image" (the file name) and "split" ("train", "test", or
// what a writer chooses, e.g. "pseudo"). Runs write it beside point_cloud.ply; `gaps render --path FILE.json`
// and the viewer read it.
#include <filesystem>
#include <string>
#include <vector>

#include <nlohmann/json_fwd.hpp>
#include "absl/status/statusor.h"
#include "gs_trainer/scene/camera.h"

namespace gaps {

struct CameraRecord {
  Camera camera;
  std::string split;  // "train", "test", ...; empty when unknown
};

// One entry (id is its place in the list).
nlohmann::json camera_json(const Camera& camera, int id, const std::string& split = "");
nlohmann::json cameras_json(const std::vector<CameraRecord>& cameras);

// Reads entries written by us or by the reference code (no cx, cy: the image centre). Every camera passes
// check_camera; errors name `where` and the entry.
absl::StatusOr<CameraRecord> parse_camera_json(const nlohmann::json& entry, const std::string& where);
absl::StatusOr<std::vector<CameraRecord>> parse_cameras_json(const nlohmann::json& list, const std::string& where);

// transforms.json's `transform_matrix` of a camera: camera-to-world, 4x4, OpenGL axes (y up, z backwards).
nlohmann::json transform_matrix_json(const Camera& camera);

absl::Status write_cameras_json(const std::filesystem::path& path, const std::vector<CameraRecord>& cameras);
absl::StatusOr<std::vector<CameraRecord>> read_cameras_json(const std::filesystem::path& path);

}  // namespace gaps

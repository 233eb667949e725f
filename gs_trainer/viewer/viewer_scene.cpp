#include "gs_trainer/viewer/viewer_scene.h"

#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "common/io_util.h"
#include "common/status_macros.h"
#include "gs_trainer/model/gaussians.h"
#include "gs_trainer/scene/cameras_json.h"
#include "gs_trainer/scene/run_files.h"
#include "gs_trainer/viewer/pack.h"

namespace gaps::viewer {
namespace {

namespace fs = std::filesystem;
using nlohmann::json;

// A JSON file of the run, or null when the run has none; a file that is there but unreadable is an error.
absl::StatusOr<json> optional_json(const fs::path& path) {
  if (!fs::exists(path)) return json();
  GAPS_ASSIGN_OR_RETURN(const std::string text, read_file_bytes(path, "run file"));
  json j = json::parse(text, nullptr, false);
  if (j.is_discarded()) return absl::DataLossError(absl::StrCat(path.string(), ": not valid JSON"));
  return j;
}

void set_model(ViewerScene& out, std::string bytes, const std::string& format, int64_t count, int degree) {
  out.model_bytes = std::move(bytes);
  out.model_format = format;
  out.gaussians = count;
  out.scene["model"] = {{"format", format}, {"count", count}, {"sh_degree", degree}};
}

absl::Status load_ply(const fs::path& ply, ViewerScene& out) {
  GAPS_ASSIGN_OR_RETURN(const GaussianModel model, load_gaussians_ply(ply));
  set_model(out, pack_model(model), "packed", model.size(), effective_sh_degree(model));
  return absl::OkStatus();
}

absl::Status load_splat(const fs::path& file, ViewerScene& out) {
  GAPS_ASSIGN_OR_RETURN(std::string bytes, read_file_bytes(file, ".splat file"));
  GAPS_RETURN_IF_ERROR(check_splat_bytes(bytes, file.string()));
  const int64_t count = static_cast<int64_t>(bytes.size()) / kSplatRecordBytes;
  set_model(out, std::move(bytes), "splat", count, 0);
  out.scene["notes"].push_back(".splat file: SH degree 0, colours, opacities and rotations in 8 bits");
  return absl::OkStatus();
}

absl::Status add_cameras(const fs::path& cameras_file, ViewerScene& out) {
  if (!fs::exists(cameras_file)) {
    out.scene["notes"].push_back(absl::StrCat("no ", cameras_file.filename().string(), ": cameras not shown"));
    return absl::OkStatus();
  }
  GAPS_ASSIGN_OR_RETURN(const std::vector<CameraRecord> cameras, read_cameras_json(cameras_file));
  for (const CameraRecord& c : cameras) out.scene["cameras"].push_back(viewer_camera_json(c.camera, c.split));
  return absl::OkStatus();
}

// One selected pseudo-view of a phase: decision, reason, pose (when phases.json has it) and thumbnail.
absl::StatusOr<json> pseudo_view_json(const json& entry, int phase, const fs::path& run, ViewerScene& out) {
  const int id = entry.value("id", -1);
  const bool admitted = entry.value("admitted", false);
  json view = {{"id", id},
               {"admitted", admitted},
               {"reason", entry.value("reason", "")},
               {"coverage", entry.value("coverage", json())},
               {"camera", nullptr},
               {"image", nullptr}};
  if (entry.contains("camera")) {
    GAPS_ASSIGN_OR_RETURN(const CameraRecord c,
                          parse_camera_json(entry["camera"], absl::StrCat("phases.json, phase ", phase)));
    view["camera"] = viewer_camera_json(c.camera, "pseudo");
  }
  const std::string image = (fs::path(kPseudoViewsFolder) / pseudo_view_file(phase, id, admitted)).generic_string();
  if (fs::exists(run / image)) {
    view["image"] = image;
    out.images.emplace_back(image, run / image);
  }
  return view;
}

absl::Status add_phases(const fs::path& run, ViewerScene& out) {
  GAPS_ASSIGN_OR_RETURN(const json phases, optional_json(run / "phases.json"));
  if (!phases.is_array()) return absl::OkStatus();
  bool any_pose = false;
  for (const json& p : phases) {
    const int number = p.value("phase", 0);
    json phase = {{"phase", number}, {"iteration", p.value("iteration", 0)}, {"tier", p.value("tier", 0)}};
    phase["views"] = json::array();
    for (const json& entry : p.value("selection", json::array())) {
      GAPS_ASSIGN_OR_RETURN(json view, pseudo_view_json(entry, number, run, out));
      any_pose |= !view["camera"].is_null();
      phase["views"].push_back(std::move(view));
    }
    out.scene["phases"].push_back(std::move(phase));
  }
  if (!phases.empty() && !any_pose) out.scene["notes"].push_back("phases.json has no pseudo-view poses to show");
  return absl::OkStatus();
}

absl::Status add_run_settings(const fs::path& run, ViewerScene& out) {
  GAPS_ASSIGN_OR_RETURN(const json metrics, optional_json(run / "metrics.json"));
  if (!metrics.is_object()) return absl::OkStatus();
  const json config = metrics.value("config", json::object());
  if (config.contains("background") && config["background"].is_number()) {
    const double b = config["background"].get<double>();
    out.scene["background"] = {b, b, b};
  }
  out.scene["title"] = absl::StrCat(fs::path(metrics.value("scene", "")).filename().string(), ", ",
                                    metrics.value("views", 0), " views, ", metrics.value("variant", ""));
  return absl::OkStatus();
}

absl::Status load_run(const fs::path& run, ViewerScene& out) {
  const fs::path ply = run / "point_cloud.ply";
  if (!fs::exists(ply))
    return absl::NotFoundError(
        absl::StrCat(run.string(), " has no point_cloud.ply (not the folder of a finished run)"));
  GAPS_RETURN_IF_ERROR(load_ply(ply, out));
  GAPS_RETURN_IF_ERROR(add_cameras(run / "cameras.json", out));
  GAPS_RETURN_IF_ERROR(add_phases(run, out));
  return add_run_settings(run, out);
}

}  // namespace

json viewer_camera_json(const Camera& camera, const std::string& split) {
  json R = json::array();
  for (int r = 0; r < 3; ++r)
    for (int c = 0; c < 3; ++c) R.push_back(camera.R(r, c));
  return {{"name", camera.name},
          {"split", split},
          {"width", camera.width},
          {"height", camera.height},
          {"fx", camera.fx},
          {"fy", camera.fy},
          {"cx", camera.cx},
          {"cy", camera.cy},
          {"R", R},
          {"t", {camera.t.x(), camera.t.y(), camera.t.z()}}};
}

absl::StatusOr<ViewerScene> load_viewer_scene(const fs::path& input) {
  if (!fs::exists(input)) return absl::NotFoundError(absl::StrCat(input.string(), " does not exist"));
  ViewerScene out;
  out.scene = {{"title", input.filename().string()},
               {"background", {0.0, 0.0, 0.0}},
               {"cameras", json::array()},
               {"phases", json::array()},
               {"notes", json::array()}};
  if (fs::is_directory(input)) {
    GAPS_RETURN_IF_ERROR(load_run(input, out));
    return out;
  }
  if (input.extension() == ".splat") {
    GAPS_RETURN_IF_ERROR(load_splat(input, out));
  } else if (input.extension() == ".ply") {
    GAPS_RETURN_IF_ERROR(load_ply(input, out));
  } else {
    return absl::InvalidArgumentError(absl::StrCat(input.string(), ": neither a run folder, a .ply nor a .splat file"));
  }
  // A model file beside a cameras.json (a run's folder, or where it was exported to) shows those cameras.
  GAPS_RETURN_IF_ERROR(add_cameras(input.parent_path() / "cameras.json", out));
  return out;
}

}  // namespace gaps::viewer

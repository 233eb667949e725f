#include "client/run_folder.h"

#include <unistd.h>

#include <algorithm>
#include <fstream>
#include <vector>

#include <nlohmann/json.hpp>
#include "absl/strings/str_cat.h"
#include "absl/strings/str_join.h"
#include "common/error_kind.h"
#include "common/io_util.h"
#include "common/status_macros.h"

namespace gaps::client {
namespace {

namespace fs = std::filesystem;

constexpr char kRecordFile[] = "run.json";

std::vector<std::string> entries(const fs::path& dir) {
  std::vector<std::string> names;
  std::error_code ec;
  for (const auto& entry : fs::directory_iterator(dir, ec)) names.push_back(entry.path().filename().string());
  std::sort(names.begin(), names.end());
  return names;
}

std::string listed(std::vector<std::string> names) {
  constexpr size_t kShown = 4;
  const size_t more = names.size() > kShown ? names.size() - kShown : 0;
  names.resize(std::min(names.size(), kShown));
  return absl::StrCat(absl::StrJoin(names, ", "), more ? absl::StrCat(" and ", more, " more") : "");
}

// Removes a file, or a folder with what it holds; a link is removed, never followed.
void remove_entry(const fs::path& path) {
  std::error_code ec;
  if (fs::is_directory(fs::symlink_status(path, ec))) remove_tree(path);
  fs::remove(path, ec);
}

// An earlier run's metrics.json says how it ended ("ok", "diverged"); "" when there is none.
std::string ended_status(const fs::path& out) {
  std::ifstream f(out / "metrics.json");
  if (!f) return "";
  const nlohmann::json j = nlohmann::json::parse(f, nullptr, /*allow_exceptions=*/false);
  return j.is_object() ? j.value("status", "unknown") : "unknown";
}

absl::Status check_resumable(const fs::path& out) {
  std::error_code ec;
  if (!fs::is_regular_file(out / kRecordFile, ec))
    return usage_error(absl::StrCat("--resume ", out.string(), ": no run to continue there (no ", kRecordFile,
                                    "; it is written when gaps train starts a run)"));
  if (const std::string status = ended_status(out); !status.empty())
    return usage_error(absl::StrCat("--resume ", out.string(), ": the run there has ended (metrics.json status \"",
                                    status, "\"); nothing to continue"));
  return absl::OkStatus();
}

std::string absolute_path(const fs::path& p) {
  if (p.empty()) return "";
  std::error_code ec;
  const fs::path a = fs::absolute(p, ec);
  return (ec ? p : a).lexically_normal().string();
}

}  // namespace

fs::path default_run_folder(const fs::path& scene_dir) {
  std::error_code ec;
  fs::path scene = fs::absolute(scene_dir, ec).lexically_normal();
  if (ec) scene = scene_dir.lexically_normal();
  if (!scene.has_filename()) scene = scene.parent_path();  // "fern/" names fern
  return fs::path("runs") / scene.filename();
}

bool has_checkpoint(const fs::path& out) {
  std::error_code ec;
  return fs::exists(out / "checkpoint" / "state.json", ec) || fs::exists(out / "checkpoint.old" / "state.json", ec);
}

void remove_checkpoint(const fs::path& out) {
  for (const char* name : {"checkpoint", "checkpoint.old", "checkpoint.partial"}) remove_entry(out / name);
}

absl::Status prepare_output_folder(const fs::path& out, FolderUse use) {
  std::error_code ec;
  if (fs::exists(out, ec) && !fs::is_directory(out, ec))
    return usage_error(absl::StrCat(out.string(), ": the output folder is a file; give a folder (new or empty)"));
  if (use == FolderUse::kResume) GAPS_RETURN_IF_ERROR(check_resumable(out));
  fs::create_directories(out, ec);
  if (ec || !fs::is_directory(out, ec))
    return usage_error(absl::StrCat(out.string(), ": cannot create the output folder (",
                                    ec ? ec.message() : "a file is in the way", ")"));
  if (::access(out.c_str(), W_OK) != 0)
    return usage_error(absl::StrCat(out.string(), ": the output folder is not writable"));
  if (use == FolderUse::kOverwrite) {
    for (const std::string& name : run_output_names()) remove_entry(out / name);
    remove_entry(out / kRecordFile);
    return absl::OkStatus();
  }
  const std::vector<std::string> present = entries(out);
  if (use == FolderUse::kFresh && !present.empty()) {
    if (has_checkpoint(out) && ended_status(out).empty())
      return usage_error(absl::StrCat(out.string(), " holds an interrupted run: continue it with gaps train --resume ",
                                      out.string(), ", or start over with --overwrite"));
    return usage_error(absl::StrCat(out.string(), " is not empty (", listed(present),
                                    "): pass --overwrite to replace an earlier run's results (other files stay), or "
                                    "choose a new folder"));
  }
  return absl::OkStatus();
}

absl::Status write_run_record(const fs::path& out, const RunRecord& record) {
  const RunOptions& o = record.options;
  const nlohmann::json j = {{"scene", absolute_path(o.scene_dir)},
                            {"views", o.views},
                            {"resolution", o.resolution},
                            {"init", o.init},
                            {"init_ply", absolute_path(o.init_ply)},
                            {"init_cache", absolute_path(o.init_cache_dir)},
                            {"random_points", o.random_points},
                            {"init_resolution", o.init_resolution},
                            {"init_options", mvs_settings_json(o)},
                            {"lpips_backbone", absolute_path(o.lpips_backbone)},
                            {"lpips_weights", absolute_path(o.lpips_weights)},
                            {"eval_every", o.eval_every},
                            {"report", o.html_report},
                            {"variant", variant_name(o.variant)},
                            {"config", o.config},
                            {"gaps", o.gaps},
                            {"backend", record.backend},
                            {"backend_options", record.backend_options}};
  return write_file_bytes(out / kRecordFile, j.dump(2) + "\n");
}

absl::StatusOr<RunRecord> read_run_record(const fs::path& out) {
  const fs::path path = out / kRecordFile;
  absl::StatusOr<std::string> text = read_file_bytes(path, "run record");
  if (!text.ok()) return input_data_error(text.status());
  const nlohmann::json j = nlohmann::json::parse(*text, nullptr, /*allow_exceptions=*/false);
  RunRecord record;
  RunOptions& o = record.options;
  try {
    o.scene_dir = j.at("scene").get<std::string>();
    o.views = j.at("views");
    o.resolution = j.at("resolution");
    o.init = j.at("init");
    o.init_ply = j.at("init_ply").get<std::string>();
    o.init_cache_dir = j.at("init_cache").get<std::string>();
    o.random_points = j.at("random_points");
    o.init_resolution = j.at("init_resolution");
    if (j.contains("init_options"))
      if (absl::Status s = read_mvs_settings(j["init_options"], o); !s.ok())
        return input_data_error(absl::DataLossError(absl::StrCat(path.string(), ": ", s.message())));
    o.lpips_backbone = j.at("lpips_backbone").get<std::string>();
    o.lpips_weights = j.at("lpips_weights").get<std::string>();
    o.eval_every = j.at("eval_every");
    o.html_report = j.at("report");
    GAPS_ASSIGN_OR_RETURN(o.variant, parse_variant(j.at("variant")));
    o.config = j.at("config").get<TrainConfig>();
    o.gaps = j.at("gaps").get<GapsConfig>();
    record.backend = j.at("backend");
    record.backend_options = j.at("backend_options");
  } catch (const std::exception& e) {
    return input_data_error(absl::DataLossError(absl::StrCat(path.string(), ": ", json_error_message(e))));
  }
  o.out_dir = out;
  return record;
}

}  // namespace gaps::client

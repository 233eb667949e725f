#pragma once
// The output folder of `gaps train`, `init` and `demo`: checked before any work (a folder, creatable,
// writable), and never a mix of two runs' results: a non-empty folder is refused unless the command reuses it
// explicitly (--overwrite first removes what an earlier run wrote; --resume continues the run it holds).
// run.json keeps a `gaps train` run's settings, so that `gaps train --resume OUT` needs nothing else.
#include <filesystem>
#include <string>

#include "absl/status/statusor.h"
#include "gs_trainer/pipeline.h"

namespace gaps::client {

enum class FolderUse { kFresh, kOverwrite, kResume };

// Creates `out` if needed and checks it can be written; kFresh refuses a non-empty folder (naming --overwrite,
// or --resume when it holds an interrupted run), kOverwrite removes an earlier run's outputs, kResume wants
// the folder of an unfinished run. Usage errors.
absl::Status prepare_output_folder(const std::filesystem::path& out, FolderUse use);

// Where `gaps train SCENE` writes without --out: runs/<the scene folder's name>, below the current folder, so
// that runs of several scenes sit side by side and none lands inside its scene. The usual rules apply to it.
std::filesystem::path default_run_folder(const std::filesystem::path& scene_dir);

// Whether `out` holds the training state of a stopped run.
bool has_checkpoint(const std::filesystem::path& out);
// A finished run needs its checkpoint no more.
void remove_checkpoint(const std::filesystem::path& out);

// What `gaps train --resume` needs besides the folder: the run's options (paths made absolute) and generator.
struct RunRecord {
  RunOptions options;
  std::string backend;
  std::string backend_options;
};
absl::Status write_run_record(const std::filesystem::path& out, const RunRecord& record);
// The record in `out`, with options.out_dir = out.
absl::StatusOr<RunRecord> read_run_record(const std::filesystem::path& out);

}  // namespace gaps::client

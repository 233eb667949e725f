#pragma once
// The flags of a run, defined once for `gaps train`, `init`, `demo` and `submit`, in the groups those commands
// take (common/cli/command_line.h), and the run they describe. `train` and `submit` take the same scene and
// training groups, so a run is described the same way whether it trains here or on a gaps-trainer.
#include <string>

#include <nlohmann/json.hpp>
#include "absl/flags/declare.h"
#include "absl/status/statusor.h"
#include "client/option_flags.h"
#include "common/cli/command_line.h"
#include "gs_trainer/pipeline.h"

namespace gaps::client {

// --scene, --views, -r/--resolution, --init, --init-ply, --random-points.
cli::FlagGroup scene_flags();
// The PatchMatch and fusion settings of --init mvs (--patchmatch-*, --fusion-*), for a run here or submitted.
cli::FlagGroup mvs_flags();
// What only an initialisation computed here uses: --init-resolution, --init-cache.
cli::FlagGroup local_init_flags();
// --variant, --config, --gaps-config, --eval-every; with training_option_flags() and gaps_option_flags().
cli::FlagGroup run_flags();
cli::FlagGroup training_option_flags();
cli::FlagGroup gaps_option_flags();
// The pseudo-view generator of an in-process run: --backend, --backend-options.
cli::FlagGroup generator_flags();
// Where an in-process run writes and what it measures: --out, --overwrite, --report, --lpips-*.
cli::FlagGroup output_flags();
// --resume, --save-every (gaps train).
cli::FlagGroup checkpoint_flags();

// A run as the flags describe it: `options` complete for an in-process run (device defaulting to cuda when
// there is one), `given` what the option files and flags set (what `gaps submit` sends).
struct FlagRun {
  RunOptions options;
  GivenOptions given;
};
// `command_defaults`: training options a command sets when neither the config file nor a flag does. Errors
// are usage errors, or input data errors for unreadable option files.
absl::StatusOr<FlagRun> run_from_flags(const nlohmann::json& command_defaults = nlohmann::json::object());

// What a run prints instead of an LPIPS value it did not compute: turned off, or the set-up's weights file
// missing (and the command that makes it).
std::string lpips_missing_note();

// The scene folder may also come as the command's one argument (gaps train SCENE); given both ways, refused.
absl::Status take_scene_argument(const cli::CommandLine& line);

}  // namespace gaps::client

ABSL_DECLARE_FLAG(std::string, scene);
ABSL_DECLARE_FLAG(int, resolution);
ABSL_DECLARE_FLAG(std::string, init_ply);
ABSL_DECLARE_FLAG(std::string, backend);
ABSL_DECLARE_FLAG(std::string, backend_options);
ABSL_DECLARE_FLAG(std::string, out);
ABSL_DECLARE_FLAG(bool, overwrite);
ABSL_DECLARE_FLAG(bool, quiet);
ABSL_DECLARE_FLAG(std::string, resume);
ABSL_DECLARE_FLAG(int, save_every);

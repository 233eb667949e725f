#pragma once
// `gaps render` and `gaps eval`: what a saved model shows and how well. Both take a run folder (gaps train's
// --out, or a fetched job's folder: its run.json or metrics.json says scene, views, resolution and background)
// or --model FILE.ply with --scene DIR --views N -r R; `gaps render --job ID` renders a finished job on its
// gaps-trainer through RenderView instead. Both return the process exit code (common/error_kind.h).
#include "common/cli/command_line.h"

namespace gaps::client {

// --path, --frames, --fps, --model, --job (render); the flags eval shares are in render_flags().
cli::FlagGroup render_flags();
// --model (eval), with scene, views, resolution, device and background from the run flags.
cli::FlagGroup model_flags();

// Renders the frames of a camera path (gs_trainer/scene/camera_path.h) as 00000.png... into --out (default
// OUT/render_<path>), their cameras as cameras.json, and an H.264 mp4 where ffmpeg is on PATH.
int run_render(const cli::CommandLine& line);
// Recomputes the metrics of a saved model on the test views of the run's split, prints them and writes
// eval.json (into the run folder, or --out).
int run_eval(const cli::CommandLine& line);

}  // namespace gaps::client

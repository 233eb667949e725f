#include "client/commands.h"

#include "absl/strings/str_cat.h"
#include "client/remote_commands.h"
#include "client/render_commands.h"
#include "client/run_flags.h"
#include "client/view_commands.h"
#include "gs_trainer/scene/scene.h"

namespace gaps::client {
namespace {

// 3DGS's train.py spellings (-s source, -m model folder, -r resolution) and -o, as every command that takes
// the long flag accepts them.
const std::map<std::string, std::string>& short_names() {
  static const auto* names =
      new std::map<std::string, std::string>{{"r", "resolution"}, {"s", "scene"}, {"m", "out"}, {"o", "out"}};
  return *names;
}

// One line instead of the table in every command's --help: the table is printed in one place.
std::string exit_codes_pointer() {
  return "exit status: 0 on success; gaps help exit-codes (or gaps --help) lists the others\n";
}

cli::CommandSpec command(std::string name, std::string synopsis, std::string summary,
                         std::vector<cli::FlagGroup> groups, int max_positional = 0, std::string positional_name = "") {
  cli::CommandSpec spec;
  spec.name = "gaps " + name;
  spec.synopsis = std::move(synopsis);
  spec.summary = std::move(summary);
  spec.groups = std::move(groups);
  // Only the short forms of flags the command takes.
  for (const auto& [short_name, long_name] : short_names())
    for (const cli::FlagGroup& group : spec.groups)
      for (const std::string& flag : group.names)
        if (flag == long_name) spec.short_names[short_name] = long_name;
  spec.max_positional = max_positional;
  spec.positional_name = std::move(positional_name);
  spec.epilogue = exit_codes_pointer();
  return spec;
}

// The run evaluates on held-out views whatever the flags, which users coming from other tools ask for.
std::map<std::string, std::string> evaluation_notes() {
  const std::string note =
      absl::StrCat("every ", kTestViewHold,
                   "th image of the scene is always held out as a test view and evaluated when the run ends "
                   "(metrics.json); --eval-every N also evaluates them every N iterations");
  return {{"eval", note}, {"evaluate", note}, {"test", note}};
}

cli::CommandSpec run_command(std::string name, std::string synopsis, std::string summary,
                             std::vector<cli::FlagGroup> groups, int max_positional = 0,
                             std::string positional_name = "") {
  cli::CommandSpec spec = command(std::move(name), std::move(synopsis), std::move(summary), std::move(groups),
                                  max_positional, std::move(positional_name));
  spec.unneeded_flags = evaluation_notes();
  return spec;
}

cli::FlagGroup only(std::string title, std::vector<std::string> names) { return {std::move(title), std::move(names)}; }

}  // namespace

std::vector<cli::CommandSpec> gaps_commands() {
  return {
      run_command(
          "train",
          "gaps train --scene DIR [--out DIR] [flags]    (the scene may also be the argument: gaps train DIR)\n"
          "       gaps train --resume OUT [--save-every N] [--quiet]",
          "Reconstructs a scene from N training views (the sparse-view split: every 8th image is a test view) and\n"
          "evaluates on the test views: point_cloud.ply, renders/, metrics.json and report.html in --out (default\n"
          "runs/<the scene folder's name>). The state is saved to OUT/checkpoint every --save-every iterations\n"
          "and on SIGINT/SIGTERM (before training began, a stop ends the run at once: nothing to save yet);\n"
          "--resume OUT continues such a run with the settings it was started with.",
          {scene_flags(), mvs_flags(), local_init_flags(), run_flags(), generator_flags(), output_flags(),
           checkpoint_flags(), training_option_flags(), gaps_option_flags()},
          1, "the scene folder"),
      command("init", "gaps init --scene DIR --views N --out DIR [flags]",
              "Writes only the initial point cloud of the training views, as points.ply and a COLMAP text model\n"
              "(sparse/0/) in --out; when the mvs method made it, also its depth and normal maps and fused cloud as a\n"
              "COLMAP dense workspace (dense/).",
              {scene_flags(), mvs_flags(), local_init_flags(), only("outputs", {"out", "overwrite"}),
               only("options", {"device", "seed"})},
              1, "the scene folder"),
      run_command(
          "demo", "gaps demo [--out DIR] [flags]",
          "Renders a small synthetic scene (16 views, 160x120) with known cameras, reconstructs it from 3 of them\n"
          "and prints the PSNR on the held-out views (default --out gaps-demo).",
          {only("initialisation", {"init", "random_points"}), run_flags(), generator_flags(), output_flags(),
           training_option_flags(), gaps_option_flags()}),
      run_command(
          "submit", "gaps submit SCENE [flags]    (or --scene DIR)",
          "Uploads a scene (its images at --resolution, undistorted, with their cameras) to a gaps-trainer as a\n"
          "job with the same scene and run flags as gaps train, and prints the job id.",
          {scene_flags(), mvs_flags(), run_flags(), submit_flags(), remote_flags(), training_option_flags(),
           gaps_option_flags()},
          1, "the scene folder"),
      command("watch", "gaps watch JOB [flags]",
              "Follows a job: progress, phases, log lines, final status; exit status 0 when it succeeded.",
              {only("display", {"quiet"}), remote_flags()}, 1, "the job id"),
      command("list", "gaps list [flags]", "Lists the trainer's jobs.", {remote_flags()}),
      command("cancel", "gaps cancel JOB [flags]", "Stops a queued or running job.", {remote_flags()}, 1, "the job id"),
      command("fetch", "gaps fetch JOB [-o DIR] [flags]",
              "Downloads a finished job's results (point_cloud.ply, metrics.json, renders/, phases.json) into DIR\n"
              "(default: a folder named after the job, JOB).",
              {only("outputs", {"out"}), remote_flags()}, 1, "the job id"),
      command("view", "gaps view OUT [--host ADDR] [--port N]    (or gaps view FILE.ply, gaps view FILE.splat)",
              "Serves the web viewer of a run folder (its point_cloud.ply, cameras.json, phases.json) or of a model\n"
              "file on --host:--port and prints the URL: the Gaussians rendered in the browser (WebGL2) as the\n"
              "rasterizer renders them, orbit and fly controls, the training and test cameras and every phase's\n"
              "pseudo-views with their admission decision. #camera=test:0&ui=0 in the URL shows test camera 0 alone.\n"
              "Ctrl-C stops it.",
              {view_flags()}, 1, "the run folder, .ply or .splat file"),
      command("export", "gaps export OUT [--format splat|html] [-o FILE]",
              "Writes a run's model (or a .ply's) as an antimatter15 .splat file (-o FILE.splat; default\n"
              "OUT/point_cloud.splat), which web splat viewers and gaps view read, or with --format html as one\n"
              "self-contained viewer page (-o FILE.html) that opens without a server. -o/--out is the file written.",
              {export_flags()}, 1, "the run folder or .ply file"),
      command("render",
              "gaps render OUT [--path auto|orbit|spiral|interp|test|FILE.json] [--frames N] [flags]\n"
              "       gaps render --model FILE.ply --scene DIR --views N -r R --path ... [flags]\n"
              "       gaps render --job ID --trainer ADDR --path ... --out DIR [flags]",
              "Renders a saved model along a camera path: orbit (around the scene's centre), spiral (LLFF-style, for\n"
              "forward-facing scenes), interp (through the training cameras in order), test (the test cameras) or\n"
              "a cameras.json file; auto (the default) is the spiral for a capture facing one way, else the orbit.\n"
              "Writes 00000.png... and cameras.json into --out (default OUT/render_<path>) and, where ffmpeg is on\n"
              "PATH, <path>.mp4 (H.264). The run folder says scene, views, resolution and background; --job renders\n"
              "a finished job on its gaps-trainer instead.",
              {render_flags(), model_flags(), only("outputs", {"out", "overwrite", "quiet"}), remote_flags()}, 1,
              "the run folder"),
      command("eval", "gaps eval OUT [flags]    (or --model FILE.ply --scene DIR --views N -r R)",
              "Recomputes the metrics of a saved model on the test views of the run's split (PSNR, SSIM, and LPIPS\n"
              "with the backbone flags), prints them and writes eval.json into the run folder (or --out);\n"
              "metrics.json stays as the run wrote it.",
              {model_flags(), only("outputs", {"out", "lpips_backbone", "lpips_weights"})}, 1, "the run folder"),
      command("options", "gaps options",
              "Prints every training and GAPS option (name, type, default, range, meaning) as a Markdown table;\n"
              "docs/options.md is its output.",
              {}),
  };
}

std::string gaps_overview() {
  return absl::StrCat(
      "usage: gaps <command> [flags]      gaps <command> --help lists the command's flags\n"
      "\n"
      "  train     reconstruct a scene from N views and evaluate on the test views (--resume continues a run)\n"
      "  init      only the initial point cloud of the training views (PLY + COLMAP text model)\n"
      "  demo      build a synthetic scene, reconstruct it from 3 views, print test PSNR\n"
      "  submit    upload a scene to a gaps-trainer (--trainer ADDR) as a job and print its id\n"
      "  watch | list | cancel | fetch    follow, list, stop or download remote jobs\n"
      "  view      serve the web viewer of a run (or a .ply / .splat) on 127.0.0.1 and print its URL\n"
      "  export    a run's model as a .splat file (or one self-contained viewer page, --format html)\n"
      "  render    frames and a video of a saved model along a camera path (orbit, spiral, interp, test, FILE.json)\n"
      "  eval      recompute a saved model's metrics on the run's test views (eval.json)\n"
      "  options   every training and GAPS option: name, type, default, range, meaning (a Markdown table)\n"
      "\n"
      "Every option is also a flag (--lambda-dssim 0.3, --n-active 24, --tier-alpha-max 1,1.5) and a key of the\n"
      "--config (training) or --gaps-config (GAPS) JSON files; a flag given on the command line wins over the file.\n"
      "Flags take dashes or underscores (--init-ply, --init_ply), --name=value or --name value; -r is --resolution,\n"
      "-s --scene, -m and -o --out. gaps --version prints the version and commit; gaps help exit-codes the table\n"
      "below.\n"
      "\n",
      cli::exit_code_table());
}

}  // namespace gaps::client

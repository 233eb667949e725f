#include "client/run_flags.h"

#include <cstdlib>
#include <filesystem>
#include <iostream>

#include <ATen/Context.h>
#include "absl/flags/flag.h"
#include "absl/strings/str_cat.h"
#include "common/cache_dir.h"
#include "common/error_kind.h"
#include "common/limits.h"
#include "common/status_macros.h"
#include "gs_trainer/eval/lpips.h"
#include "gs_trainer/gaps/config.h"

ABSL_FLAG(
    std::string, scene, "",
    "scene folder (LLFF poses_bounds.npy, COLMAP sparse/, or transforms.json); may also be the command's argument");
ABSL_FLAG(int, views, 3, "number of training views (benchmark split; <= 0 uses every non-test view)");
ABSL_FLAG(int, resolution, 8, "image downscale factor (uses images_R/ when present)");
ABSL_FLAG(std::string, init, "auto",
          "initial points: auto (mvs, or sparse when PatchMatch gives under 25% of the pixels a depth), mvs "
          "(PatchMatch stereo on the training views), sweep (the older plane sweep), sparse, random, scene or ply");
ABSL_FLAG(std::string, init_ply, "",
          "PLY for --init ply (given alone, implies it): a full 3DGS model (opacity, scale_*, rot_*: training "
          "continues it) or a coloured point cloud (Gaussians made from its points)");
ABSL_FLAG(int64_t, random_points, 20000, "number of points for --init random");
ABSL_FLAG(
    int, init_resolution, 0,
    "downscale factor of the images the initialisation (sparse, mvs, sweep) reads, e.g. 4 to triangulate from larger "
    "images than -r 8 trains on (0: --resolution)");
ABSL_FLAG(int, patchmatch_best_views, gaps::PatchMatchOptions{}.best_views,
          "mvs: a depth hypothesis's cost is the mean of its best this many source views' costs (1 suits few views, "
          "where most surfaces are seen well by one neighbour, fusion then asking two views to agree; COLMAP uses 3)");
ABSL_FLAG(double, patchmatch_max_cost, gaps::PatchMatchOptions{}.max_cost,
          "mvs: pixels whose final cost (1 - NCC plus the geometric term) is higher get no depth (higher: more, "
          "less reliable depths)");
ABSL_FLAG(int, patchmatch_iterations, gaps::PatchMatchOptions{}.iterations,
          "mvs: PatchMatch propagation sweeps (each updates the red, then the black pixels)");
ABSL_FLAG(int, patchmatch_max_image_side, gaps::PatchMatchOptions{}.max_image_side,
          "mvs: PatchMatch works on the views downsampled to this longest side");
ABSL_FLAG(bool, patchmatch_geometric_consistency, gaps::PatchMatchOptions{}.geometric_consistency,
          "mvs: the geometric-consistency pass against the other views' depth maps");
ABSL_FLAG(int, fusion_min_views, gaps::FusionOptions{}.min_views,
          "mvs: views (the reference included) that must agree on a pixel's point for fusion to keep it");
ABSL_FLAG(double, fusion_max_normal_error, gaps::FusionOptions{}.max_normal_error_deg,
          "mvs: largest angle in degrees between the normals of pixels fused into one point");
ABSL_FLAG(bool, fusion_add_sparse, gaps::FusionOptions{}.add_sparse_points,
          "mvs: add the sparse stage's triangulated points to the fused cloud (they reach surfaces PatchMatch leaves "
          "without depth)");
ABSL_FLAG(int, sparse_max_image_side, gaps::SparseOptions{}.max_image_side,
          "mvs, sweep, sparse: SIFT and triangulation work on the views downsampled to this longest side, so that "
          "--init-resolution can give PatchMatch larger views without slowing SIFT (0: the views as read)");
ABSL_FLAG(std::string, init_cache, "",
          "folder caching initial point clouds (default: $GAPS_CACHE/init or ~/.cache/gaps/init)");
ABSL_FLAG(std::string, variant, "vanilla", "vanilla, full (the paper's method), no-gaps or no-dropgaussian");
ABSL_FLAG(std::string, config, "",
          "JSON file of training options (the names `gaps options` lists under training); flags win over it");
ABSL_FLAG(std::string, gaps_config, "",
          "JSON file of GAPS options (the names `gaps options` lists under gaps); flags win over it");
ABSL_FLAG(int, eval_every, gaps::kDefaultEvalEvery,
          "evaluate the test views every N iterations into metrics.json's curve (0: only at the end)");
ABSL_FLAG(std::string, backend, "reproject", "pseudo-view generator backend for the method variants");
ABSL_FLAG(std::string, backend_options, "", "JSON object of backend options");
ABSL_FLAG(std::string, out, "", "output folder (gaps export: the file written)");
ABSL_FLAG(bool, overwrite, false,
          "reuse a non-empty output folder: first remove what an earlier run wrote there (other files stay)");
ABSL_FLAG(bool, report, true, "write report.html (metrics, curve, renders next to ground truth, pseudo-views)");
ABSL_FLAG(bool, quiet, false, "no progress output");
ABSL_FLAG(std::string, lpips_weights, "",
          "LPIPS-VGG weights (default: the file scripts/setup.sh makes, ~/.cache/gaps/lpips/"
          "vgg16_lpips_v0.1.safetensors, when present; none: no LPIPS); with --lpips-backbone, lpips' v0.1 vgg.pth");
ABSL_FLAG(std::string, lpips_backbone, "",
          "a torchvision VGG16 state dict (vgg16-397923af.pth) to pair with --lpips-weights vgg.pth instead of the "
          "set-up's file");
ABSL_FLAG(std::string, resume, "",
          "continue the interrupted run in this output folder, with the settings it was started with");
ABSL_FLAG(int, save_every, 2000,
          "save the training state to OUT/checkpoint every N iterations, besides on SIGINT/SIGTERM (0: only then)");

namespace gaps::client {
namespace {

std::filesystem::path default_init_cache() {
  const std::filesystem::path cache = gaps_cache_dir();
  return cache.empty() ? cache : cache / "init";
}

// --lpips-weights empty: the set-up's file if it is there (a file that is there but broken is an error when
// the run loads it); when it is not, LPIPS is null and the run says why (lpips_missing_note()).
absl::Status lpips_from_flags(RunOptions& o) {
  const std::string weights = absl::GetFlag(FLAGS_lpips_weights);
  o.lpips_backbone = absl::GetFlag(FLAGS_lpips_backbone);
  if (weights == kLpipsOff) {
    if (!o.lpips_backbone.empty()) return usage_error("--lpips-backbone with --lpips-weights=none: pick one");
    o.lpips_weights.clear();
    return absl::OkStatus();
  }
  if (!weights.empty()) {
    o.lpips_weights = weights;
    return absl::OkStatus();
  }
  if (!o.lpips_backbone.empty()) return usage_error("--lpips-backbone needs --lpips-weights (lpips' v0.1 vgg.pth)");
  std::error_code ec;
  const std::filesystem::path set_up = default_lpips_weights_path();
  o.lpips_weights = !set_up.empty() && std::filesystem::exists(set_up, ec) ? set_up : std::filesystem::path();
  return absl::OkStatus();
}

// A method run too short for its first diffusion phase trains as vanilla 3DGS would, which nothing else
// would say until one reads phases.json.
void warn_if_no_diffusion_phase(const RunOptions& o) {
  if (o.variant == Variant::kVanilla || num_diffusion_phases(o.config.iterations, o.gaps) > 0) return;
  std::cerr << "warning: --variant " << variant_name(o.variant) << " with " << o.config.iterations
            << " iterations runs no diffusion phase (the first comes after warmup_iterations = "
            << o.gaps.warmup_iterations << "): give --iterations " << iterations_for_first_phase(o.gaps)
            << " or more, or a lower --warmup-iterations\n";
}

}  // namespace

std::string lpips_missing_note() {
  const std::string weights = absl::GetFlag(FLAGS_lpips_weights);
  if (weights == kLpipsOff) return "off (--lpips-weights=none)";
  return absl::StrCat("n/a (no LPIPS weights at ", default_lpips_weights_path().string(),
                      ": bash scripts/setup.sh makes them)");
}

cli::FlagGroup scene_flags() {
  return {"scene", {"scene", "views", "resolution", "init", "init_ply", "random_points"}};
}
cli::FlagGroup mvs_flags() {
  return {"PatchMatch initialisation (--init mvs)",
          {"patchmatch_best_views", "patchmatch_max_cost", "patchmatch_iterations", "patchmatch_max_image_side",
           "patchmatch_geometric_consistency", "fusion_min_views", "fusion_max_normal_error", "fusion_add_sparse",
           "sparse_max_image_side"}};
}
cli::FlagGroup local_init_flags() { return {"initialisation", {"init_resolution", "init_cache"}}; }
cli::FlagGroup run_flags() { return {"run", {"variant", "config", "gaps_config", "eval_every"}}; }
cli::FlagGroup training_option_flags() {
  return {"training options (gaps options lists them; also keys of --config)", training_option_flag_names()};
}
cli::FlagGroup gaps_option_flags() {
  return {"GAPS options (gaps options lists them; also keys of --gaps-config)", gaps_option_flag_names()};
}
cli::FlagGroup generator_flags() { return {"pseudo-view generator", {"backend", "backend_options"}}; }
cli::FlagGroup output_flags() {
  return {"outputs", {"out", "overwrite", "report", "quiet", "lpips_backbone", "lpips_weights"}};
}
cli::FlagGroup checkpoint_flags() { return {"checkpoints", {"save_every", "resume"}}; }

absl::StatusOr<FlagRun> run_from_flags(const nlohmann::json& command_defaults) {
  FlagRun run;
  RunOptions& o = run.options;
  o.scene_dir = absl::GetFlag(FLAGS_scene);
  o.views = absl::GetFlag(FLAGS_views);
  o.resolution = absl::GetFlag(FLAGS_resolution);
  o.init = absl::GetFlag(FLAGS_init);
  o.init_ply = absl::GetFlag(FLAGS_init_ply);
  if (!o.init_ply.empty()) o.init = "ply";
  o.random_points = absl::GetFlag(FLAGS_random_points);
  o.init_resolution = absl::GetFlag(FLAGS_init_resolution);
  o.patchmatch.best_views = absl::GetFlag(FLAGS_patchmatch_best_views);
  o.patchmatch.max_cost = absl::GetFlag(FLAGS_patchmatch_max_cost);
  o.patchmatch.iterations = absl::GetFlag(FLAGS_patchmatch_iterations);
  o.patchmatch.max_image_side = absl::GetFlag(FLAGS_patchmatch_max_image_side);
  o.patchmatch.geometric_consistency = absl::GetFlag(FLAGS_patchmatch_geometric_consistency);
  o.fusion.min_views = absl::GetFlag(FLAGS_fusion_min_views);
  o.fusion.max_normal_error_deg = absl::GetFlag(FLAGS_fusion_max_normal_error);
  o.fusion.add_sparse_points = absl::GetFlag(FLAGS_fusion_add_sparse);
  o.sparse.max_image_side = absl::GetFlag(FLAGS_sparse_max_image_side);
  o.init_cache_dir = absl::GetFlag(FLAGS_init_cache);
  if (o.init_cache_dir.empty()) o.init_cache_dir = default_init_cache();
  GAPS_RETURN_IF_ERROR(lpips_from_flags(o));
  o.eval_every = absl::GetFlag(FLAGS_eval_every);
  o.html_report = absl::GetFlag(FLAGS_report);
  if (o.eval_every < 0) return usage_error("--eval-every must be 0 or positive");
  if (o.resolution <= 0) return usage_error("--resolution must be positive");
  if (absl::Status s = check_gaussian_count("--random-points", o.random_points); !s.ok())
    return usage_error(s.message());
  const absl::StatusOr<Variant> variant = parse_variant(absl::GetFlag(FLAGS_variant));
  if (!variant.ok()) return usage_error(absl::StrCat("--variant: ", variant.status().message()));
  o.variant = *variant;
  GAPS_ASSIGN_OR_RETURN(run.given,
                        options_from_files_and_flags(absl::GetFlag(FLAGS_config), absl::GetFlag(FLAGS_gaps_config)));
  for (const std::string& note : run.given.notes) std::cerr << "gaps: " << note << "\n";
  // Options neither the file nor a flag gives: the command's own defaults, and the GPU when there is one.
  nlohmann::json training = run.given.training;
  for (auto it = command_defaults.begin(); it != command_defaults.end(); ++it)
    if (!training.contains(it.key())) training[it.key()] = it.value();
  if (!training.contains("device")) training["device"] = at::hasCUDA() ? "cuda" : "cpu";
  try {
    o.config = training.get<TrainConfig>();
    o.gaps = run.given.gaps.get<GapsConfig>();
  } catch (const std::exception& e) {
    return usage_error(json_error_message(e));
  }
  warn_if_no_diffusion_phase(o);
  return run;
}

absl::Status take_scene_argument(const cli::CommandLine& line) {
  if (line.positional.empty()) return absl::OkStatus();
  if (line.has("scene"))
    return usage_error(absl::StrCat("two scene folders: --scene ", absl::GetFlag(FLAGS_scene), " and ",
                                    line.positional[0], "; give one"));
  absl::SetFlag(&FLAGS_scene, line.positional[0]);
  return absl::OkStatus();
}

}  // namespace gaps::client

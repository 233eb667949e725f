// gaps: the command line. Standalone subcommands run in this process:
//   gaps train --scene DIR --views N --resolution R --iterations K --seed S --device cpu|cuda --out DIR
//   gaps demo  [--out DIR] [--iterations K]
// Remote subcommands talk to a gaps-trainer service (client/remote_commands.h):
//   gaps submit SCENE --views N ... --trainer ADDR | watch JOB | list | cancel JOB | fetch JOB -o DIR
#include <algorithm>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <iostream>
#include <string>
#include <vector>

#include <ATen/Context.h>
#include <nlohmann/json.hpp>
#include "absl/flags/flag.h"
#include "absl/flags/parse.h"
#include "absl/flags/usage.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "client/option_flags.h"
#include "client/remote_commands.h"
#include "common/status_macros.h"
#include "diffusion_worker/backend_registry.h"
#include "gs_trainer/pipeline.h"
#include "gs_trainer/synthetic.h"
#include "gs_trainer/train/divergence.h"

ABSL_FLAG(std::string, scene, "", "scene folder (LLFF poses_bounds.npy, COLMAP sparse/, or transforms.json)");
ABSL_FLAG(int, views, 3, "number of training views (benchmark split; <= 0 uses every non-test view)");
ABSL_FLAG(int, resolution, 8, "image downscale factor (uses images_R/ when present)");
ABSL_FLAG(std::string, out, "", "output folder (PLY, renders, metrics.json)");
ABSL_FLAG(std::string, init, "auto",
          "initial points: auto (mvs for forward-facing views, sparse for views that surround the scene), mvs (from "
          "the training views), sparse, random, scene or ply");
ABSL_FLAG(std::string, init_cache, "",
          "folder caching initial point clouds (default: $GAPS_CACHE/init or ~/.cache/gaps/init)");
ABSL_FLAG(std::string, init_ply, "", "PLY point cloud for --init ply (given alone, implies it)");
ABSL_FLAG(int64_t, random_points, 20000, "number of points for --init random");
ABSL_FLAG(int, init_resolution, 0,
          "downscale factor of the images the initialisation (sparse, mvs) reads, e.g. 4 to triangulate from larger "
          "images than -r 8 trains on (0: --resolution)");
ABSL_FLAG(std::string, config, "",
          "JSON file of training options (the names `gaps options` lists under training); flags win over it");
ABSL_FLAG(std::string, lpips_backbone, "", "VGG16 weights (torchvision vgg16-397923af.pth); LPIPS is null without");
ABSL_FLAG(std::string, lpips_weights, "", "LPIPS v0.1 linear weights (vgg.pth)");
ABSL_FLAG(bool, quiet, false, "no progress bar");
ABSL_FLAG(std::string, variant, "vanilla", "vanilla, full (the paper's method), no-gaps or no-dropgaussian");
ABSL_FLAG(std::string, backend, "reproject", "pseudo-view generator backend for the method variants");
ABSL_FLAG(std::string, backend_options, "", "JSON object of backend options");
ABSL_FLAG(std::string, gaps_config, "",
          "JSON file of GAPS options (the names `gaps options` lists under gaps); flags win over it");
ABSL_FLAG(int, eval_every, 1000,
          "evaluate the test views every N iterations into metrics.json's curve (0: only at the end)");
ABSL_FLAG(bool, report, true, "write report.html (metrics, curve, renders next to ground truth, pseudo-views)");

namespace {

constexpr char kUsage[] =
    "gaps <command> [flags]\n"
    "  train   reconstruct a scene from N views and evaluate on the test views\n"
    "  init    only the initial point cloud of the training views (PLY + COLMAP text model)\n"
    "  demo    build a synthetic scene, reconstruct it from 3 views, print test PSNR\n"
    "  submit SCENE   upload a scene to a gaps-trainer (--trainer ADDR) and print the job id\n"
    "  watch JOB | list | cancel JOB | fetch JOB -o DIR   follow, list, stop or download remote jobs\n"
    "  options   every training and GAPS option: name, type, default, range, meaning (a Markdown table)\n"
    "Every option is also a flag (--lambda-dssim 0.3, --n-active 24, --tier-alpha-max 1,1.5) and a key of the\n"
    "--config (training) or --gaps-config (GAPS) JSON files; a flag given on the command line wins over the file.\n"
    "Flags accept dashes or underscores (--init-ply or --init_ply).";

void print_progress(const gaps::TrainProgress& p) {
  const int width = 30;
  const int filled = static_cast<int>(width * static_cast<double>(p.iteration) / p.iterations);
  const double eta = p.iterations_per_second > 0 ? (p.iterations - p.iteration) / p.iterations_per_second : 0;
  std::fprintf(stderr, "\r[%s%s] %6d/%d  loss %.4f  %8lld Gaussians  %6.1f it/s  ETA %02d:%02d ",
               std::string(filled, '#').c_str(), std::string(width - filled, '.').c_str(), p.iteration, p.iterations,
               p.loss, static_cast<long long>(p.num_gaussians), p.iterations_per_second, static_cast<int>(eta) / 60,
               static_cast<int>(eta) % 60);
  if (p.iteration == p.iterations) std::fprintf(stderr, "\n");
}

// absl flags are identifiers; accept the dashed spellings users type (--init-ply).
std::vector<char*> normalise_flag_names(int argc, char** argv, std::vector<std::string>& storage) {
  storage.assign(argv, argv + argc);
  for (auto& a : storage) {
    if (a.rfind("--", 0) != 0) continue;
    const size_t end = std::min(a.find('='), a.size());
    for (size_t i = 2; i < end; ++i)
      if (a[i] == '-') a[i] = '_';
  }
  std::vector<char*> out;
  for (auto& a : storage) out.push_back(a.data());
  return out;
}

// `command_defaults`: training options a command sets when neither the config file nor a flag does.
absl::StatusOr<gaps::RunOptions> options_from_flags(const nlohmann::json& command_defaults = nlohmann::json::object()) {
  gaps::RunOptions o;
  o.views = absl::GetFlag(FLAGS_views);
  o.resolution = absl::GetFlag(FLAGS_resolution);
  o.init = absl::GetFlag(FLAGS_init);
  o.init_ply = absl::GetFlag(FLAGS_init_ply);
  if (!o.init_ply.empty()) o.init = "ply";
  o.random_points = absl::GetFlag(FLAGS_random_points);
  o.init_resolution = absl::GetFlag(FLAGS_init_resolution);
  o.init_cache_dir = absl::GetFlag(FLAGS_init_cache);
  if (o.init_cache_dir.empty()) {
    const char* cache = std::getenv("GAPS_CACHE");
    const char* home = std::getenv("HOME");
    if (cache)
      o.init_cache_dir = std::filesystem::path(cache) / "init";
    else if (home)
      o.init_cache_dir = std::filesystem::path(home) / ".cache" / "gaps" / "init";
  }
  o.lpips_backbone = absl::GetFlag(FLAGS_lpips_backbone);
  o.lpips_weights = absl::GetFlag(FLAGS_lpips_weights);
  GAPS_ASSIGN_OR_RETURN(o.variant, gaps::parse_variant(absl::GetFlag(FLAGS_variant)));
  GAPS_ASSIGN_OR_RETURN(
      gaps::client::GivenOptions given,
      gaps::client::options_from_files_and_flags(absl::GetFlag(FLAGS_config), absl::GetFlag(FLAGS_gaps_config)));
  for (const std::string& note : given.notes) std::cerr << "gaps: " << note << "\n";
  // Options neither the file nor a flag gives: the command's own defaults.
  for (auto it = command_defaults.begin(); it != command_defaults.end(); ++it)
    if (!given.training.contains(it.key())) given.training[it.key()] = it.value();
  if (!given.training.contains("device")) given.training["device"] = at::hasCUDA() ? "cuda" : "cpu";
  try {
    o.config = given.training.get<gaps::TrainConfig>();
    o.gaps = given.gaps.get<gaps::GapsConfig>();
  } catch (const std::exception& e) {
    return absl::InvalidArgumentError(gaps::json_error_message(e));
  }
  o.eval_every = absl::GetFlag(FLAGS_eval_every);
  o.html_report = absl::GetFlag(FLAGS_report);
  if (o.eval_every < 0) return absl::InvalidArgumentError("--eval-every must be 0 or positive");
  if (o.resolution <= 0) return absl::InvalidArgumentError("--resolution must be positive");
  return o;
}

int report(const absl::StatusOr<gaps::RunResult>& result, const gaps::RunOptions& o) {
  if (!result.ok()) {
    std::cerr << "gaps: " << result.status().message() << "\n";
    // A diverged run is a result (metrics.json says "diverged"), not a crash: its own exit status.
    return gaps::is_divergence(result.status()) ? 3 : 1;
  }
  const auto& m = result->metrics;
  std::cout << absl::StrFormat("test PSNR %.2f dB  SSIM %.4f  LPIPS %s  |  %d Gaussians  |  %.1f s training\n", m.psnr,
                               m.ssim, m.lpips ? absl::StrFormat("%.4f", *m.lpips) : "n/a (no backbone)",
                               result->num_gaussians, result->train_seconds);
  if (result->degraded())
    std::cout << "DEGRADED: " << result->phases_skipped << " of " << result->phases
              << " diffusion phases were skipped (no generator answered)\n";
  std::cout << "outputs in " << o.out_dir.string() << " (point_cloud.ply, renders/, metrics.json"
            << (o.html_report ? ", report.html)\n" : ")\n");
  return 0;
}

auto progress_printer() {
  const bool quiet = absl::GetFlag(FLAGS_quiet);
  return [quiet](const gaps::TrainProgress& p) {
    if (!quiet) print_progress(p);
  };
}

void log_line(const std::string& s) { std::cerr << s << "\n"; }

// The command line as typed (flag names normalised), for defaults that depend on whether a flag was given.
std::vector<std::string> storage_;

bool flag_given(const std::vector<std::string>& args, const std::string& name) {
  return std::any_of(args.begin(), args.end(),
                     [&](const std::string& a) { return a == name || a.rfind(name + "=", 0) == 0; });
}

// Runs the pipeline with the generator the flags ask for (only the method variants use one).
absl::StatusOr<gaps::RunResult> run_with_generator(gaps::RunOptions& o) {
  std::unique_ptr<gaps::Generator> generator;
  if (o.variant != gaps::Variant::kVanilla) {
    GAPS_ASSIGN_OR_RETURN(generator,
                          gaps::make_generator(absl::GetFlag(FLAGS_backend), absl::GetFlag(FLAGS_backend_options)));
    o.generator = generator.get();
  }
  return gaps::run_pipeline(o, progress_printer(), log_line);
}

int run_train() {
  auto options = options_from_flags();
  if (!options.ok()) {
    std::cerr << "gaps train: " << options.status().message() << "\n";
    return 2;
  }
  options->scene_dir = absl::GetFlag(FLAGS_scene);
  options->out_dir = absl::GetFlag(FLAGS_out);
  if (options->scene_dir.empty() || options->out_dir.empty()) {
    std::cerr << "gaps train: --scene and --out are required\n";
    return 2;
  }
  return report(run_with_generator(*options), *options);
}

int run_init() {
  auto options = options_from_flags();
  if (!options.ok()) {
    std::cerr << "gaps init: " << options.status().message() << "\n";
    return 2;
  }
  options->scene_dir = absl::GetFlag(FLAGS_scene);
  options->out_dir = absl::GetFlag(FLAGS_out);
  if (options->scene_dir.empty() || options->out_dir.empty()) {
    std::cerr << "gaps init: --scene and --out are required\n";
    return 2;
  }
  if (auto st = gaps::run_init_only(*options, log_line); !st.ok()) {
    std::cerr << "gaps init: " << st.message() << "\n";
    return 1;
  }
  return 0;
}

int run_demo() {
  // The demo's own budget, unless the user chose one.
  auto options = options_from_flags({{"iterations", 1500}});
  if (!options.ok()) {
    std::cerr << "gaps demo: " << options.status().message() << "\n";
    return 2;
  }
  const std::string out = absl::GetFlag(FLAGS_out);
  options->out_dir = out.empty() ? std::filesystem::path("gaps-demo") : std::filesystem::path(out);
  options->scene_dir = options->out_dir / "scene";
  options->resolution = 1;
  options->views = 3;
  // Three 160x120 views carry too few features for the MVS initialiser (it would fall back anyway), and a
  // small random cloud keeps the demo within minutes on two cores.
  if (!flag_given(storage_, "--init")) options->init = "random";
  if (!flag_given(storage_, "--random_points")) options->random_points = 5000;
  std::cerr << "demo: rendering a synthetic scene (16 views, 160x120) into " << options->scene_dir << "\n";
  if (auto st = gaps::write_synthetic_scene(options->scene_dir, {}); !st.ok()) {
    std::cerr << "gaps demo: " << st.message() << "\n";
    return 1;
  }
  std::cerr << "demo: reconstructing from 3 views, evaluating on the held-out test views\n";
  return report(run_with_generator(*options), *options);
}

// The option tables as Markdown: docs/options.md is this output.
int print_options() {
  std::cout << "| section | option | type | default | range | meaning |\n|---|---|---|---|---|---|\n";
  for (const auto& table : {gaps::train_config_options(), gaps::gaps_config_options()}) {
    for (const gaps::OptionInfo& o : table) {
      const bool ranged = std::isfinite(o.min) && std::isfinite(o.max) && o.type != "bool" && o.type != "std::string";
      std::string help = o.help;
      for (size_t at = help.find('|'); at != std::string::npos; at = help.find('|', at + 2)) help.replace(at, 1, "\\|");
      std::cout << "| " << o.section << " | `" << o.name << "` | " << o.type << " | `" << o.default_value.dump()
                << "` | " << (ranged ? absl::StrCat("[", o.min, ", ", o.max, "]") : "") << " | " << help << " |\n";
    }
  }
  return 0;
}

}  // namespace

int main(int argc, char** argv) {
  absl::SetProgramUsageMessage(kUsage);
  std::vector<std::string>& storage = storage_;
  std::vector<char*> args = normalise_flag_names(argc, argv, storage);
  const std::vector<char*> positional = absl::ParseCommandLine(static_cast<int>(args.size()), args.data());
  const std::string command = positional.size() > 1 ? positional[1] : "";
  if (command == "train") return run_train();
  if (command == "init") return run_init();
  if (gaps::client::is_remote_command(command))
    return gaps::client::run_remote_command(command,
                                            std::vector<std::string>(positional.begin() + 2, positional.end()));
  if (command == "demo") return run_demo();
  if (command == "options") return print_options();
  std::cerr << kUsage << "\n";
  return 2;
}

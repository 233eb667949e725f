#include "client/local_commands.h"

#include <unistd.h>

#include <algorithm>
#include <atomic>
#include <cmath>
#include <csignal>
#include <cstring>
#include <iostream>
#include <memory>

#include "absl/flags/flag.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "absl/strings/str_join.h"
#include "client/progress.h"
#include "client/run_flags.h"
#include "client/run_folder.h"
#include "common/device.h"
#include "common/error_kind.h"
#include "common/status_macros.h"
#include "diffusion_worker/backend_registry.h"
#include "gs_trainer/synthetic.h"

namespace gaps::client {
namespace {

// The signal that asked a `gaps train` run to stop (0: none): the run saves its state and ends at the next
// iteration. A second signal ends the process the default way, for a run stuck before its next iteration.
std::atomic<int> g_stop_signal{0};
// Set just before training's first iteration. Before it (reading the scene, the initialisation, which takes
// minutes on a CPU) there is no state to save, so a stop signal ends the process at once with
// g_stopped_early_message; finished initialisations are already in the cache.
std::atomic<bool> g_training{false};
std::string g_stopped_early_message;

extern "C" void on_stop_signal(int signal) {
  if (!g_training.load()) {
    // Only async-signal-safe calls here: the message was formatted beforehand.
    (void)!write(STDERR_FILENO, g_stopped_early_message.data(), g_stopped_early_message.size());
    _exit(128 + signal);
  }
  if (g_stop_signal.exchange(signal) == 0) return;
  std::signal(signal, SIG_DFL);
  std::raise(signal);
}

int fail(const std::string& command, const absl::Status& status) {
  std::cerr << "gaps " << command << ": " << status.message() << "\n";
  return exit_code(status);
}

// The result; with --quiet in one line (a degraded run's warning aside).
int report(const std::string& command, const absl::StatusOr<RunResult>& result, const RunOptions& o) {
  if (!result.ok()) return fail(command, result.status());
  const auto& m = result->metrics;
  const bool quiet = absl::GetFlag(FLAGS_quiet);
  if (result->degraded())
    std::cerr << "warning: DEGRADED: " << result->phases_skipped << " of " << result->phases
              << " diffusion phases were skipped (no generator answered)\n";
  std::cout << absl::StrFormat("test PSNR %.2f dB  SSIM %.4f  LPIPS %s  |  %d Gaussians  |  %.1f s training", m.psnr,
                               m.ssim, m.lpips ? absl::StrFormat("%.4f", *m.lpips) : lpips_missing_note(),
                               result->num_gaussians, result->train_seconds);
  if (quiet) {
    std::cout << "  |  outputs in " << o.out_dir.string() << "\n";
    return 0;
  }
  std::cout << "\noutputs in " << o.out_dir.string() << " (point_cloud.ply, renders/, metrics.json"
            << (o.html_report ? ", report.html)\n" : ")\n");
  return 0;
}

// Runs the pipeline with the generator the flags ask for (only the method variants use one), progress and
// log lines on stderr.
absl::StatusOr<RunResult> run_with_generator(RunOptions& o, const std::string& backend,
                                             const std::string& backend_options) {
  std::unique_ptr<Generator> generator;
  if (o.variant != Variant::kVanilla) {
    GAPS_ASSIGN_OR_RETURN(generator, make_generator(backend, backend_options));
    o.generator = generator.get();
  }
  ProgressPrinter progress(absl::GetFlag(FLAGS_quiet));
  const auto on_progress = [&](const TrainProgress& p) {
    progress.print({p.iteration, p.iterations, p.loss, p.num_gaussians, p.iterations_per_second});
  };
  const bool quiet = absl::GetFlag(FLAGS_quiet);
  const auto log = [&](const std::string& line) {
    if (quiet && !is_warning(line)) return;
    progress.end_line();
    std::cerr << line << "\n";
  };
  absl::StatusOr<RunResult> result = run_pipeline(o, on_progress, log);
  progress.end_line();
  return result;
}

// The cheap checks before a generator is loaded or a scene read: a known backend, a device, the scene.
absl::Status check_run(const RunOptions& o, const std::string& backend) {
  if (o.variant != Variant::kVanilla) {
    const std::vector<std::string> known = known_generator_backends();
    if (std::find(known.begin(), known.end(), backend) == known.end())
      return usage_error(absl::StrCat("--backend ", backend, ": unknown; one of ", absl::StrJoin(known, ", ")));
  }
  GAPS_RETURN_IF_ERROR(check_device(o.config.device));
  return check_scene(o);
}

// `gaps train --resume OUT`: the run recorded there. Only what does not change the run may be given again.
absl::StatusOr<RunRecord> resumed_run(const cli::CommandLine& line) {
  const std::filesystem::path out = absl::GetFlag(FLAGS_resume);
  for (const std::string& name : line.given)
    if (name != "resume" && name != "save_every" && name != "quiet")
      return usage_error(absl::StrCat("--resume continues the run with the settings it was started with (",
                                      (out / "run.json").string(), "); ", cli::display_name(name),
                                      " cannot change them (only --save-every and --quiet may be given)"));
  if (!line.positional.empty()) return usage_error("--resume takes no scene argument: the run recorded it");
  GAPS_RETURN_IF_ERROR(prepare_output_folder(out, FolderUse::kResume));
  return read_run_record(out);
}

absl::StatusOr<RunRecord> new_run(const cli::CommandLine& line) {
  GAPS_RETURN_IF_ERROR(take_scene_argument(line));
  GAPS_ASSIGN_OR_RETURN(const FlagRun run, run_from_flags());
  RunRecord record{run.options, absl::GetFlag(FLAGS_backend), absl::GetFlag(FLAGS_backend_options)};
  RunOptions& o = record.options;
  if (o.scene_dir.empty()) return usage_error("the scene folder is missing: gaps train SCENE or --scene DIR");
  o.out_dir = absl::GetFlag(FLAGS_out);
  if (o.out_dir.empty()) {
    o.out_dir = default_run_folder(o.scene_dir);
    if (!absl::GetFlag(FLAGS_quiet)) std::cerr << "no --out given: the run goes to " << o.out_dir.string() << "\n";
  }
  return record;
}

void install_stop_handlers() {
  std::signal(SIGINT, on_stop_signal);
  std::signal(SIGTERM, on_stop_signal);
}

}  // namespace

int run_train(const cli::CommandLine& line) {
  const bool resuming = line.has("resume");
  absl::StatusOr<RunRecord> record = resuming ? resumed_run(line) : new_run(line);
  if (!record.ok()) return fail("train", record.status());
  RunOptions& o = record->options;
  o.checkpoint_every = absl::GetFlag(FLAGS_save_every);
  if (o.checkpoint_every < 0) return fail("train", usage_error("--save-every must be 0 or positive"));
  if (absl::Status st = check_run(o, record->backend); !st.ok()) return fail("train", st);
  if (!resuming) {
    const FolderUse use = absl::GetFlag(FLAGS_overwrite) ? FolderUse::kOverwrite : FolderUse::kFresh;
    if (absl::Status st = prepare_output_folder(o.out_dir, use); !st.ok()) return fail("train", st);
    if (absl::Status st = write_run_record(o.out_dir, *record); !st.ok()) return fail("train", st);
  } else if (!has_checkpoint(o.out_dir)) {
    std::cerr << "warning: no checkpoint in " << o.out_dir.string() << " yet: the run starts over with its settings\n";
  }
  o.checkpoint_dir = o.out_dir / "checkpoint";
  int saved_at = -1;
  o.on_checkpoint = [&](int iteration) {
    saved_at = iteration;
    if (!absl::GetFlag(FLAGS_quiet)) std::cerr << "checkpoint at iteration " << iteration << "\n";
  };
  o.should_stop = [] { return g_stop_signal.load() != 0; };
  o.on_training_started = [] { g_training = true; };
  g_stopped_early_message =
      absl::StrCat("gaps train: stopped before training began, with nothing to save; gaps train --resume ",
                   o.out_dir.string(), " starts it again (a finished initialisation is reused from the cache)\n");
  install_stop_handlers();
  const absl::StatusOr<RunResult> result = run_with_generator(o, record->backend, record->backend_options);
  if (const int signal = g_stop_signal.load(); signal != 0 && absl::IsCancelled(result.status())) {
    std::cerr << "gaps train: stopped by " << (signal == SIGINT ? "SIGINT" : "SIGTERM")
              << (saved_at >= 0
                      ? absl::StrCat(" at iteration ", saved_at, "; the run is saved in ", o.checkpoint_dir.string(),
                                     ": continue it with gaps train --resume ", o.out_dir.string())
                      : "; the checkpoint could not be written (see above)")
              << "\n";
    return 128 + signal;
  }
  const int code = report("train", result, o);
  if (result.ok()) remove_checkpoint(o.out_dir);
  return code;
}

int run_init(const cli::CommandLine& line) {
  if (absl::Status st = take_scene_argument(line); !st.ok()) return fail("init", st);
  absl::StatusOr<FlagRun> run = run_from_flags();
  if (!run.ok()) return fail("init", run.status());
  RunOptions& o = run->options;
  o.out_dir = absl::GetFlag(FLAGS_out);
  if (o.scene_dir.empty() || o.out_dir.empty())
    return fail("init", usage_error("--scene and --out are required (gaps init --help)"));
  if (absl::Status st = check_run(o, ""); !st.ok()) return fail("init", st);
  const FolderUse use = absl::GetFlag(FLAGS_overwrite) ? FolderUse::kOverwrite : FolderUse::kFresh;
  if (absl::Status st = prepare_output_folder(o.out_dir, use); !st.ok()) return fail("init", st);
  if (absl::Status st = run_init_only(o, [](const std::string& s) { std::cerr << s << "\n"; }); !st.ok())
    return fail("init", st);
  return 0;
}

int run_demo(const cli::CommandLine& line) {
  // The demo's own budget, unless the user chose one.
  absl::StatusOr<FlagRun> run = run_from_flags({{"iterations", 1500}});
  if (!run.ok()) return fail("demo", run.status());
  RunOptions& o = run->options;
  const std::string out = absl::GetFlag(FLAGS_out);
  o.out_dir = out.empty() ? std::filesystem::path("gaps-demo") : std::filesystem::path(out);
  o.scene_dir = o.out_dir / "scene";
  o.resolution = 1;
  o.views = 3;
  // Three 160x120 views carry too few features for the MVS initialiser (it would fall back anyway), and a
  // small random cloud keeps the demo within minutes on two cores and below the automatic Gaussian budget,
  // so that densification has room to grow.
  if (!line.has("init")) o.init = "random";
  if (!line.has("random_points")) o.random_points = 2000;
  const FolderUse use = absl::GetFlag(FLAGS_overwrite) ? FolderUse::kOverwrite : FolderUse::kFresh;
  if (absl::Status st = prepare_output_folder(o.out_dir, use); !st.ok()) return fail("demo", st);
  const bool quiet = absl::GetFlag(FLAGS_quiet);
  if (!quiet) std::cerr << "demo: rendering a synthetic scene (16 views, 160x120) into " << o.scene_dir << "\n";
  if (absl::Status st = write_synthetic_scene(o.scene_dir, {}); !st.ok()) return fail("demo", st);
  if (absl::Status st = check_run(o, absl::GetFlag(FLAGS_backend)); !st.ok()) return fail("demo", st);
  if (!quiet) std::cerr << "demo: reconstructing from 3 views, evaluating on the held-out test views\n";
  return report("demo", run_with_generator(o, absl::GetFlag(FLAGS_backend), absl::GetFlag(FLAGS_backend_options)), o);
}

// The option tables as Markdown: docs/options.md is this output.
int print_options() {
  std::cout << "| section | option | type | default | range | meaning |\n|---|---|---|---|---|---|\n";
  for (const auto& table : {train_config_options(), gaps_config_options()}) {
    for (const OptionInfo& o : table) {
      std::string help = o.help;
      for (size_t at = help.find('|'); at != std::string::npos; at = help.find('|', at + 2)) help.replace(at, 1, "\\|");
      std::cout << "| " << o.section << " | `" << o.name << "` | " << option_type_words(o.type) << " | `"
                << o.default_value.dump() << "` | " << option_range_words(o) << " | " << help << " |\n";
    }
  }
  return 0;
}

}  // namespace gaps::client

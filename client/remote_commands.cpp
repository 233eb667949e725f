#include "client/remote_commands.h"

#include <unistd.h>

#include <cstdio>
#include <fstream>
#include <iostream>

#include <nlohmann/json.hpp>
#include "absl/flags/flag.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "client/progress.h"
#include "client/remote_client.h"
#include "client/run_flags.h"
#include "common/error_kind.h"
#include "common/io_util.h"
#include "common/ply.h"
#include "common/printable.h"
#include "common/status_macros.h"
#include "gs_trainer/scene/scene.h"
#include "rpc/config_codec.h"

ABSL_FLAG(std::string, trainer, "127.0.0.1:50051", "address of the gaps-trainer service");
ABSL_FLAG(std::string, token_file, "", "file holding the bearer token (default: $GAPS_TOKEN)");
ABSL_FLAG(std::string, tls_ca, "", "CA certificate of the trainer's TLS (default: plaintext)");
ABSL_FLAG(std::string, tls_server_name, "", "name the trainer's certificate is checked against");
ABSL_FLAG(std::string, tls_client_cert, "", "client certificate (PEM), for a trainer that requires one (mutual TLS)");
ABSL_FLAG(std::string, tls_client_key, "", "private key of --tls-client-cert");
ABSL_FLAG(std::string, name, "", "job name (default: the scene folder's name)");
ABSL_FLAG(bool, watch, false, "keep watching the job until it ends");

namespace gaps::client {

absl::StatusOr<TrainerClient> connect_trainer() {
  absl::StatusOr<std::string> token = rpc::load_token(absl::GetFlag(FLAGS_token_file));
  if (!token.ok()) return input_data_error(token.status());
  GAPS_ASSIGN_OR_RETURN(
      TrainerClient client,
      TrainerClient::connect(absl::GetFlag(FLAGS_trainer),
                             {*token, absl::GetFlag(FLAGS_tls_ca), absl::GetFlag(FLAGS_tls_server_name),
                              absl::GetFlag(FLAGS_tls_client_cert), absl::GetFlag(FLAGS_tls_client_key)}));
  GAPS_RETURN_IF_ERROR(client.check_reachable(std::chrono::seconds(10)));
  return client;
}

namespace {

// The job `gaps train` would run with the same flags, checked as there (the scene included) so that a job is
// refused before its upload; only the options the files and flags set are sent (the trainer has the defaults).
// *options: the run's options.
absl::StatusOr<v1::JobSpec> spec_from_flags(RunOptions* options) {
  GAPS_ASSIGN_OR_RETURN(const FlagRun run, run_from_flags());
  const RunOptions& o = run.options;
  *options = o;
  if (o.scene_dir.empty()) return usage_error("the scene folder is missing (gaps submit SCENE or --scene DIR)");
  GAPS_RETURN_IF_ERROR(check_scene(o));
  v1::JobSpec spec;
  const std::string name = absl::GetFlag(FLAGS_name);
  spec.set_name(!name.empty() ? name : o.scene_dir.lexically_normal().filename().string());
  v1::TrainConfig* c = spec.mutable_config();
  c->set_views(o.views);
  // A PLY file and the scene's own points both travel as the upload's points (see scene_points_ply).
  c->set_init(o.init == "ply" || o.init == "scene" ? "points" : o.init);
  c->set_random_points(o.random_points);
  c->set_variant(variant_name(o.variant));
  c->set_eval_every(o.eval_every);
  GAPS_RETURN_IF_ERROR(rpc::set_fields(run.given.training, c->mutable_training()));
  GAPS_RETURN_IF_ERROR(rpc::set_fields(run.given.gaps, c->mutable_gaps()));
  // Only the initialisation settings that differ from the defaults (the trainer has the defaults).
  GAPS_RETURN_IF_ERROR(rpc::set_fields(changed_mvs_settings(o), c->mutable_init_settings()));
  return spec;
}

// --init scene: the points the scene ships (COLMAP points3D), as a PLY file's bytes. The upload carries images
// and cameras only, so they go as the job's initial points: the job starts from the cloud gaps train starts from.
absl::StatusOr<std::string> scene_points_ply(const RunOptions& o) {
  GAPS_ASSIGN_OR_RETURN(const Scene scene, load_scene(o.scene_dir, SceneLoadOptions{o.resolution, ""}));
  if (!scene.points)
    return absl::FailedPreconditionError(o.scene_dir.string() + ": --init scene needs the scene's own points");
  const std::filesystem::path file =
      std::filesystem::temp_directory_path() / absl::StrCat("gaps-scene-points-", getpid(), ".ply");
  absl::Status written = write_point_cloud_ply(*scene.points, file);
  absl::StatusOr<std::string> bytes = written.ok() ? read_file_bytes(file, "scene points") : written;
  std::error_code ignored;
  std::filesystem::remove(file, ignored);
  return bytes;
}

// With --quiet only the warnings: a skipped phase and the job's own warning lines.
bool quiet_keeps(const v1::JobEvent& e) {
  return (e.has_phase_finished() && e.phase_finished().skipped()) || (e.has_log() && is_warning(e.log()));
}

void print_event(const v1::JobEvent& e, ProgressPrinter& progress) {
  if (e.has_progress()) {
    const v1::Progress& p = e.progress();
    progress.print({p.iteration(), p.iterations(), p.loss(), p.num_gaussians(), p.iterations_per_second()});
    return;
  }
  if (absl::GetFlag(FLAGS_quiet) && !quiet_keeps(e)) return;
  progress.end_line();
  if (e.has_phase_started())
    std::fprintf(stderr, "phase %d started at iteration %d\n", e.phase_started().phase(),
                 e.phase_started().iteration());
  if (e.has_phase_finished()) {
    const v1::PhaseEvent& p = e.phase_finished();
    if (p.skipped())
      std::fprintf(stderr, "phase %d SKIPPED: %s\n", p.phase(), printable(p.skip_reason()).c_str());
    else
      std::fprintf(stderr, "phase %d finished: %d selected, %d admitted\n", p.phase(), p.selected(), p.admitted());
  }
  if (e.has_log()) std::fprintf(stderr, "%s\n", printable(e.log(), /*keep_lines=*/true).c_str());
  if (e.has_state_changed()) std::fprintf(stderr, "state: %s\n", v1::JobState_Name(e.state_changed()).c_str());
  if (e.has_checkpoint_written()) std::fprintf(stderr, "checkpoint at iteration %d\n", e.checkpoint_written());
}

void print_status(const v1::JobStatus& s) {
  // A running job that has not trained yet is still making its initial points (minutes on a CPU).
  const bool initialising = s.state() == v1::RUNNING && s.stage() == "initialising";
  std::cout << absl::StrFormat("%s  %-12s  %-16s  %6d/%-6d  %8lld Gaussians", s.job_id(),
                               initialising ? "INITIALISING" : v1::JobState_Name(s.state()), printable(s.name()),
                               s.iteration(), s.iterations(), static_cast<long long>(s.num_gaussians()));
  if (s.state() == v1::SUCCEEDED) {
    std::cout << absl::StrFormat("  PSNR %.2f  SSIM %.4f", s.psnr(), s.ssim());
    std::cout << (s.has_lpips() ? absl::StrFormat("  LPIPS %.4f", s.lpips()) : std::string("  LPIPS n/a"));
  }
  if (s.degraded())
    std::cout << absl::StrFormat("  DEGRADED: %d of %d diffusion phases skipped", s.phases_skipped(), s.phases());
  if (!s.error().empty()) std::cout << "  " << printable(s.error());
  std::cout << "\n";
}

int job_exit_code(const v1::JobStatus& s) { return s.state() == v1::SUCCEEDED ? 0 : 1; }

absl::StatusOr<int> watch(TrainerClient& client, const std::string& job_id) {
  ProgressPrinter progress(absl::GetFlag(FLAGS_quiet));
  GAPS_ASSIGN_OR_RETURN(v1::JobStatus final_status,
                        client.watch(job_id, [&](const v1::JobEvent& e) { print_event(e, progress); }));
  progress.end_line();
  print_status(final_status);
  return job_exit_code(final_status);
}

// Why a job that ended has nothing to fetch, and what to do about it.
absl::Status no_artifacts_error(const v1::JobStatus& s) {
  const std::string job = absl::StrCat("job ", s.job_id());
  if (s.state() == v1::CANCELLED && s.started_at() == 0)
    return absl::FailedPreconditionError(absl::StrCat(
        job, " has no artifacts: it was cancelled before it ran (gaps submit the scene again to train it)"));
  if (s.state() == v1::CANCELLED)
    return absl::FailedPreconditionError(absl::StrCat(job, " has no artifacts: it was cancelled at iteration ",
                                                      s.iteration(), " of ", s.iterations(), ", before writing any"));
  if (s.state() == v1::FAILED)
    return absl::FailedPreconditionError(
        absl::StrCat(job, " has no artifacts: it failed before writing any (", printable(s.error()), ")"));
  return absl::FailedPreconditionError(
      absl::StrCat(job, " has no artifacts (state ", v1::JobState_Name(s.state()), ")"));
}

// Into -o DIR, or a folder named after the job; a job that left nothing is an error saying why.
absl::StatusOr<int> fetch(TrainerClient& client, const std::string& job_id) {
  std::string out = absl::GetFlag(FLAGS_out);
  if (out.empty()) out = job_id;
  GAPS_ASSIGN_OR_RETURN(const std::vector<std::string> files, client.fetch(job_id, out));
  if (files.empty()) {
    GAPS_ASSIGN_OR_RETURN(const v1::JobStatus status, client.get(job_id));
    return no_artifacts_error(status);
  }
  for (const auto& f : files) std::cout << (std::filesystem::path(out) / f).string() << "\n";
  return 0;
}

absl::StatusOr<int> submit() {
  RunOptions o;
  GAPS_ASSIGN_OR_RETURN(const v1::JobSpec spec, spec_from_flags(&o));
  GAPS_ASSIGN_OR_RETURN(TrainerClient client, connect_trainer());
  absl::StatusOr<PreparedScene> scene = prepare_scene(o.scene_dir, o.resolution);
  if (!scene.ok()) return input_data_error(scene.status());
  if (absl::Status larger = add_larger_training_views(o, &*scene); absl::IsNotFound(larger)) {
    if (!absl::GetFlag(FLAGS_quiet))
      std::fprintf(stderr,
                   "init: auto: no views at twice the training size for PatchMatch (%s): the trainer reads the "
                   "training views\n",
                   std::string(larger.message()).c_str());
  } else if (!larger.ok()) {
    return input_data_error(larger);
  }
  if (const std::string ply = absl::GetFlag(FLAGS_init_ply); !ply.empty()) {
    absl::StatusOr<std::string> points = read_file_bytes(ply, "point cloud");
    if (!points.ok()) return input_data_error(points.status());
    scene->points_ply = std::move(*points);
  } else if (o.init == "scene") {
    absl::StatusOr<std::string> points = scene_points_ply(o);
    if (!points.ok()) return input_data_error(points.status());
    scene->points_ply = std::move(*points);
  }
  GAPS_ASSIGN_OR_RETURN(std::string job_id, client.submit(spec, *scene));
  std::cout << job_id << std::endl;
  if (absl::GetFlag(FLAGS_watch)) return watch(client, job_id);
  return 0;
}

absl::StatusOr<int> run(const std::string& command, const cli::CommandLine& line) {
  if (command == "submit") {
    GAPS_RETURN_IF_ERROR(take_scene_argument(line));
    return submit();
  }
  const auto need_argument = [&](const char* what) -> absl::Status {
    if (line.positional.size() != 1) return usage_error(absl::StrCat("gaps ", command, " takes one argument: ", what));
    return absl::OkStatus();
  };
  const std::vector<std::string>& args = line.positional;
  if (command != "list") GAPS_RETURN_IF_ERROR(need_argument("the job id"));
  GAPS_ASSIGN_OR_RETURN(TrainerClient client, connect_trainer());
  if (command == "watch") return watch(client, args[0]);
  if (command == "list") {
    GAPS_ASSIGN_OR_RETURN(std::vector<v1::JobStatus> jobs, client.list());
    for (const auto& j : jobs) print_status(j);
    return 0;
  }
  if (command == "cancel") {
    GAPS_ASSIGN_OR_RETURN(v1::JobStatus status, client.cancel(args[0]));
    print_status(status);
    return 0;
  }
  if (command == "fetch") return fetch(client, args[0]);
  return usage_error(absl::StrCat("unknown command ", command));
}

}  // namespace

cli::FlagGroup remote_flags() {
  return {"trainer service",
          {"trainer", "token_file", "tls_ca", "tls_server_name", "tls_client_cert", "tls_client_key"}};
}

cli::FlagGroup submit_flags() { return {"job", {"name", "watch", "quiet"}}; }

bool is_remote_command(const std::string& command) {
  return command == "submit" || command == "watch" || command == "list" || command == "cancel" || command == "fetch";
}

int run_remote_command(const std::string& command, const cli::CommandLine& line) {
  absl::StatusOr<int> code = run(command, line);
  if (!code.ok()) {
    std::cerr << "gaps " << command << ": " << code.status().message() << "\n";
    return gaps::exit_code(code.status());
  }
  return *code;
}

}  // namespace gaps::client

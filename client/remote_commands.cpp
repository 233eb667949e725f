#include "client/remote_commands.h"

#include <cstdio>
#include <fstream>
#include <iostream>

#include <nlohmann/json.hpp>
#include "absl/flags/declare.h"
#include "absl/flags/flag.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "client/option_flags.h"
#include "client/remote_client.h"
#include "common/io_util.h"
#include "common/status_macros.h"
#include "gs_trainer/gaps/config.h"
#include "gs_trainer/train/train_config.h"
#include "rpc/config_codec.h"

// Shared with `gaps train` (defined in gaps_main.cpp).
ABSL_DECLARE_FLAG(int, views);
ABSL_DECLARE_FLAG(int, resolution);
ABSL_DECLARE_FLAG(std::string, init);
ABSL_DECLARE_FLAG(std::string, init_ply);
ABSL_DECLARE_FLAG(int64_t, random_points);
ABSL_DECLARE_FLAG(std::string, config);
ABSL_DECLARE_FLAG(std::string, gaps_config);
ABSL_DECLARE_FLAG(std::string, variant);
ABSL_DECLARE_FLAG(std::string, out);
ABSL_DECLARE_FLAG(bool, quiet);

ABSL_FLAG(std::string, trainer, "127.0.0.1:50051", "address of the gaps-trainer service");
ABSL_FLAG(std::string, token_file, "", "file holding the bearer token (default: $GAPS_TOKEN)");
ABSL_FLAG(std::string, tls_ca, "", "CA certificate of the trainer's TLS (default: plaintext)");
ABSL_FLAG(std::string, tls_server_name, "", "name the trainer's certificate is checked against");
ABSL_FLAG(std::string, tls_client_cert, "", "client certificate (PEM), for a trainer that requires one (mutual TLS)");
ABSL_FLAG(std::string, tls_client_key, "", "private key of --tls_client_cert");
ABSL_FLAG(std::string, name, "", "job name (default: the scene folder's name)");
ABSL_FLAG(bool, watch, false, "submit: keep watching the job until it ends");
ABSL_FLAG(std::string, o, "", "fetch: output folder (same as --out)");

namespace gaps::client {
namespace {

absl::StatusOr<TrainerClient> connect() {
  GAPS_ASSIGN_OR_RETURN(std::string token, rpc::load_token(absl::GetFlag(FLAGS_token_file)));
  return TrainerClient::connect(absl::GetFlag(FLAGS_trainer),
                                {token, absl::GetFlag(FLAGS_tls_ca), absl::GetFlag(FLAGS_tls_server_name),
                                 absl::GetFlag(FLAGS_tls_client_cert), absl::GetFlag(FLAGS_tls_client_key)});
}

absl::StatusOr<v1::JobSpec> spec_from_flags(const std::string& scene) {
  v1::JobSpec spec;
  const std::string name = absl::GetFlag(FLAGS_name);
  spec.set_name(!name.empty() ? name : std::filesystem::path(scene).lexically_normal().filename().string());
  v1::TrainConfig* c = spec.mutable_config();
  c->set_views(absl::GetFlag(FLAGS_views));
  std::string init = absl::GetFlag(FLAGS_init);
  if (!absl::GetFlag(FLAGS_init_ply).empty()) init = "points";
  c->set_init(init);
  c->set_random_points(absl::GetFlag(FLAGS_random_points));
  c->set_variant(absl::GetFlag(FLAGS_variant));
  // The same files and flags as `gaps train`, checked here as there, so that a job is refused before its upload.
  GAPS_ASSIGN_OR_RETURN(GivenOptions given,
                        options_from_files_and_flags(absl::GetFlag(FLAGS_config), absl::GetFlag(FLAGS_gaps_config)));
  for (const std::string& note : given.notes) std::cerr << "gaps: " << note << "\n";
  try {
    (void)given.training.get<TrainConfig>();
    (void)given.gaps.get<GapsConfig>();
  } catch (const std::exception& e) {
    return absl::InvalidArgumentError(json_error_message(e));
  }
  GAPS_RETURN_IF_ERROR(rpc::set_fields(given.training, c->mutable_training()));
  GAPS_RETURN_IF_ERROR(rpc::set_fields(given.gaps, c->mutable_gaps()));
  return spec;
}

void print_event(const v1::JobEvent& e, bool quiet) {
  if (e.has_progress()) {
    if (quiet) return;
    const v1::Progress& p = e.progress();
    const int width = 30;
    const int filled =
        p.iterations() > 0 ? static_cast<int>(width * static_cast<double>(p.iteration()) / p.iterations()) : 0;
    std::fprintf(stderr, "\r[%s%s] %6d/%d  loss %.4f  %8lld Gaussians  %6.1f it/s ", std::string(filled, '#').c_str(),
                 std::string(width - filled, '.').c_str(), p.iteration(), p.iterations(), p.loss(),
                 static_cast<long long>(p.num_gaussians()), p.iterations_per_second());
    if (p.iteration() == p.iterations()) std::fprintf(stderr, "\n");
    return;
  }
  if (e.has_phase_started())
    std::fprintf(stderr, "\nphase %d started at iteration %d\n", e.phase_started().phase(),
                 e.phase_started().iteration());
  if (e.has_phase_finished()) {
    const v1::PhaseEvent& p = e.phase_finished();
    if (p.skipped())
      std::fprintf(stderr, "\nphase %d SKIPPED: %s\n", p.phase(), p.skip_reason().c_str());
    else
      std::fprintf(stderr, "\nphase %d finished: %d selected, %d admitted\n", p.phase(), p.selected(), p.admitted());
  }
  if (e.has_log()) std::fprintf(stderr, "%s\n", e.log().c_str());
  if (e.has_state_changed()) std::fprintf(stderr, "state: %s\n", v1::JobState_Name(e.state_changed()).c_str());
  if (e.has_checkpoint_written()) std::fprintf(stderr, "checkpoint at iteration %d\n", e.checkpoint_written());
}

void print_status(const v1::JobStatus& s) {
  std::cout << absl::StrFormat("%s  %-9s  %-16s  %6d/%-6d  %8lld Gaussians", s.job_id(), v1::JobState_Name(s.state()),
                               s.name(), s.iteration(), s.iterations(), static_cast<long long>(s.num_gaussians()));
  if (s.state() == v1::SUCCEEDED) std::cout << absl::StrFormat("  PSNR %.2f  SSIM %.4f", s.psnr(), s.ssim());
  if (s.degraded())
    std::cout << absl::StrFormat("  DEGRADED: %d of %d diffusion phases skipped", s.phases_skipped(), s.phases());
  if (!s.error().empty()) std::cout << "  " << s.error();
  std::cout << "\n";
}

int exit_code(const v1::JobStatus& s) { return s.state() == v1::SUCCEEDED ? 0 : 1; }

absl::StatusOr<int> watch(TrainerClient& client, const std::string& job_id) {
  const bool quiet = absl::GetFlag(FLAGS_quiet);
  GAPS_ASSIGN_OR_RETURN(v1::JobStatus final_status,
                        client.watch(job_id, [quiet](const v1::JobEvent& e) { print_event(e, quiet); }));
  print_status(final_status);
  return exit_code(final_status);
}

absl::StatusOr<int> run(const std::string& command, const std::vector<std::string>& args) {
  GAPS_ASSIGN_OR_RETURN(TrainerClient client, connect());
  const auto need_argument = [&](const char* what) -> absl::Status {
    if (args.size() != 1)
      return absl::InvalidArgumentError(absl::StrCat("gaps ", command, " takes one argument: ", what));
    return absl::OkStatus();
  };
  if (command == "submit") {
    GAPS_RETURN_IF_ERROR(need_argument("the scene folder"));
    GAPS_ASSIGN_OR_RETURN(v1::JobSpec spec, spec_from_flags(args[0]));
    GAPS_ASSIGN_OR_RETURN(PreparedScene scene, prepare_scene(args[0], absl::GetFlag(FLAGS_resolution)));
    if (const std::string ply = absl::GetFlag(FLAGS_init_ply); !ply.empty()) {
      GAPS_ASSIGN_OR_RETURN(scene.points_ply, read_file_bytes(ply, "point cloud"));
    }
    GAPS_ASSIGN_OR_RETURN(std::string job_id, client.submit(spec, scene));
    std::cout << job_id << std::endl;
    if (absl::GetFlag(FLAGS_watch)) return watch(client, job_id);
    return 0;
  }
  if (command == "watch") {
    GAPS_RETURN_IF_ERROR(need_argument("the job id"));
    return watch(client, args[0]);
  }
  if (command == "list") {
    GAPS_ASSIGN_OR_RETURN(std::vector<v1::JobStatus> jobs, client.list());
    for (const auto& j : jobs) print_status(j);
    return 0;
  }
  if (command == "cancel") {
    GAPS_RETURN_IF_ERROR(need_argument("the job id"));
    GAPS_ASSIGN_OR_RETURN(v1::JobStatus status, client.cancel(args[0]));
    print_status(status);
    return 0;
  }
  if (command == "fetch") {
    GAPS_RETURN_IF_ERROR(need_argument("the job id"));
    std::string out = absl::GetFlag(FLAGS_o);
    if (out.empty()) out = absl::GetFlag(FLAGS_out);
    if (out.empty()) return absl::InvalidArgumentError("gaps fetch needs -o DIR");
    GAPS_ASSIGN_OR_RETURN(std::vector<std::string> files, client.fetch(args[0], out));
    for (const auto& f : files) std::cout << (std::filesystem::path(out) / f).string() << "\n";
    return 0;
  }
  return absl::InvalidArgumentError(absl::StrCat("unknown command ", command));
}

}  // namespace

bool is_remote_command(const std::string& command) {
  return command == "submit" || command == "watch" || command == "list" || command == "cancel" || command == "fetch";
}

int run_remote_command(const std::string& command, const std::vector<std::string>& args) {
  absl::StatusOr<int> code = run(command, args);
  if (!code.ok()) {
    std::cerr << "gaps " << command << ": " << code.status().message() << "\n";
    return code.status().code() == absl::StatusCode::kInvalidArgument ? 2 : 1;
  }
  return *code;
}

}  // namespace gaps::client

// gaps-trainer: the training service (gaps.v1.Trainer) with its job queue and SQLite job store.
//   gaps-trainer --listen 127.0.0.1:50051 --workers 127.0.0.1:50052[,ADDR...] --data-dir DIR --device cpu|cuda:0
//                [--concurrency N] [--threads-per-job N] [--token-file F] [--tls-cert F --tls-key F [--tls-client-ca
//                F]]
//                [--worker-token-file F] [--worker-tls-ca F [--worker-tls-cert F --worker-tls-key F]]
// SIGTERM/SIGINT: running jobs stop at their next iteration, write a checkpoint and stay RUNNING in the
// store; the next trainer started on the same data folder resumes them from it.
#include <unistd.h>

#include <cstdlib>
#include <filesystem>

#include <grpcpp/grpcpp.h>
#include "absl/flags/flag.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_split.h"
#include "common/cli/command_line.h"
#include "common/device.h"
#include "common/error_kind.h"
#include "common/io_util.h"
#include "gs_trainer/eval/lpips.h"
#include "rpc/security.h"
#include "rpc/service_main.h"
#include "rpc/shared_memory.h"
#include "server/trainer_service.h"

ABSL_FLAG(std::string, listen, "127.0.0.1:50051", "address to serve on (a bare port binds 127.0.0.1)");
ABSL_FLAG(std::string, workers, "",
          "diffusion workers (needed by the method variants): HOST:PORT[,HOST:PORT...], or dns:///NAME:PORT for "
          "every address NAME resolves to at each job's start (e.g. a Kubernetes headless Service)");
ABSL_FLAG(std::string, data_dir, "gaps-trainer-data", "folder of the job database, uploaded scenes and outputs");
ABSL_FLAG(std::string, job_store, "",
          "job store: empty for SQLite in --data_dir (this trainer alone), or postgresql://USER:PASSWORD@HOST:PORT/DB "
          "shared by trainer replicas that also share --data_dir (default: $GAPS_JOB_STORE)");
ABSL_FLAG(double, lease_seconds, 30, "a job whose trainer stops renewing its lease for this long is taken over");
ABSL_FLAG(std::string, replica_id, "", "this trainer's name in leases and logs (default: host-pid-random)");
ABSL_FLAG(std::string, device, "cpu", "training device (cpu, cuda, cuda:N)");
ABSL_FLAG(int, concurrency, 1, "jobs trained at once");
ABSL_FLAG(int, threads_per_job, 0,
          "CPU threads of each job's parallel regions (0: the process's threads, OMP_NUM_THREADS or its cores, "
          "shared out among the --concurrency jobs)");
ABSL_FLAG(double, checkpoint_seconds, 120,
          "a running job saves its state at least this often (seconds of wall time; 0: only at the diffusion "
          "phases and on shutdown), so a trainer killed without warning loses at most that much work");
ABSL_FLAG(int, max_crashes, 2,
          "a job whose trainer died this many times while running it is FAILED at the next start instead of run again");
ABSL_FLAG(std::string, worker_token_file, "",
          "token sent to the workers (default: $GAPS_WORKER_TOKEN, else none; the trainer's own token is never sent, "
          "so that whoever runs a worker address cannot drive the trainer)");
ABSL_FLAG(std::string, worker_tls_ca, "", "CA certificate of the workers' TLS (default: plaintext)");
ABSL_FLAG(std::string, worker_tls_server_name, "", "name the workers' certificates are checked against");
ABSL_FLAG(std::string, worker_tls_cert, "", "this trainer's client certificate, for workers that require one");
ABSL_FLAG(std::string, worker_tls_key, "", "private key of --worker-tls-cert");
ABSL_FLAG(int, worker_timeout_s, 300, "deadline of each generation call");
ABSL_FLAG(int, worker_rounds, 3, "passes over the worker pool (with backoff) before a phase is skipped");
ABSL_FLAG(std::string, worker_encoding, "compact",
          "how renders and images travel to and from the workers: compact (colour and alpha as bytes, depth as "
          "float16 in the messages, float32 through shared memory) or float32 (what an in-process backend sees, "
          "bit for bit)");
ABSL_FLAG(bool, worker_shared_memory, true,
          "pass payloads through shared memory to workers that share this host's /dev/shm (found out per worker; "
          "the others get them in the messages)");
ABSL_FLAG(bool, worker_fan_out, true,
          "spread each diffusion phase's pseudo-views over every reachable worker at once (each worker is adapted to "
          "the scene, LoRA training included); false: one worker per phase, the others stand by for failover");
ABSL_FLAG(double, worker_adaptation_grace_s, 1.0,
          "with --worker-fan-out, a phase waits for the workers' scene adaptation until one has ended and this many "
          "seconds more; a worker still adapting then sits out the phases until its adaptation ends (a value as long "
          "as --worker-timeout-s waits for every worker)");
ABSL_FLAG(bool, worker_share_adaptation, true,
          "with --worker-fan-out, the first worker of --workers adapts to the scene (LoRA training) and the others "
          "install what it learnt instead of each training its own (list first a worker whose GPU is not the "
          "trainer's); false: every worker adapts itself");
ABSL_FLAG(uint64_t, max_upload_mb, 8192, "largest accepted scene upload in MiB");
ABSL_FLAG(std::string, lpips_weights, "",
          "LPIPS-VGG weights of the jobs' metrics (default: ~/.cache/gaps/lpips/vgg16_lpips_v0.1.safetensors, as "
          "scripts/setup.sh makes it, when present; none: no LPIPS)");

ABSL_FLAG(std::string, init_cache, "",
          "folder of the initial point clouds the jobs reuse (default: DATA_DIR/init_cache); gaps train's own "
          "(~/.cache/gaps/init) shares one cache between the two on a machine");

namespace {

gaps::cli::CommandSpec command() {
  gaps::cli::CommandSpec spec;
  spec.name = "gaps-trainer";
  spec.synopsis = "gaps-trainer --listen ADDR --workers ADDR[,ADDR...] --data-dir DIR --device DEV [flags]";
  spec.summary =
      "The training service: accepts scenes from gaps submit, trains them as jobs (the method variants with\n"
      "pseudo-views from gaps-worker services) and serves their results. SIGTERM/SIGINT stop it gracefully;\n"
      "a trainer started again on the same --data-dir resumes the interrupted jobs. Replicas sharing a PostgreSQL\n"
      "--job-store (and one --data-dir) share the queue: a replica that dies has its jobs taken over.\n"
      "--tryfromenv=NAME,... takes those flags from FLAGS_NAME environment variables when set.";
  spec.groups = {
      {"service",
       {"listen", "data_dir", "device", "gpu_memory_gib", "concurrency", "threads_per_job", "max_crashes",
        "max_upload_mb", "checkpoint_seconds", "lpips_weights", "init_cache"}},
      {"job store (replicas)", {"job_store", "replica_id", "lease_seconds"}},
      {"security", gaps::rpc::security_flag_names()},
      {"diffusion workers",
       {"workers", "worker_token_file", "worker_tls_ca", "worker_tls_server_name", "worker_tls_cert", "worker_tls_key",
        "worker_timeout_s", "worker_rounds", "worker_encoding", "worker_shared_memory", "worker_fan_out",
        "worker_adaptation_grace_s", "worker_share_adaptation"}},
  };
  spec.epilogue = gaps::cli::exit_code_table();
  return spec;
}

int fail(const absl::Status& status) {
  gaps::write_log_line(STDERR_FILENO, absl::StrCat("gaps-trainer: ", status.message()));
  return gaps::exit_code(status);
}

int usage(const std::string& message) { return fail(gaps::usage_error(message)); }

// Token and TLS files are the input data of a service.
int fail_reading(const absl::Status& status) { return fail(gaps::input_data_error(status)); }

// The jobs' LPIPS weights, checked now rather than at the end of every job: an explicit file must load; the
// set-up's file is used when it is there (and must load); without it jobs report LPIPS as null, which
// `note` says at start.
absl::StatusOr<std::filesystem::path> lpips_weights(std::string* note) {
  const std::string flag = absl::GetFlag(FLAGS_lpips_weights);
  if (flag == gaps::kLpipsOff) {
    *note = "no LPIPS (--lpips-weights=none)";
    return std::filesystem::path();
  }
  std::filesystem::path path = flag.empty() ? gaps::default_lpips_weights_path() : std::filesystem::path(flag);
  std::error_code ec;
  if (flag.empty() && (path.empty() || !std::filesystem::exists(path, ec))) {
    *note = absl::StrCat("no LPIPS: no weights at ", path.string(), " (bash scripts/setup.sh makes them)");
    return std::filesystem::path();
  }
  absl::StatusOr<gaps::Lpips> loaded = gaps::Lpips::load_safetensors(path.string());
  if (!loaded.ok()) return gaps::input_data_error(loaded.status());
  *note = absl::StrCat("LPIPS from ", path.string());
  return path;
}

int serve() {
  const std::string device = absl::GetFlag(FLAGS_device);
  if (absl::Status st = gaps::check_device(device); !st.ok()) return fail(st);
  if (absl::Status st = gaps::rpc::apply_gpu_memory_cap(device); !st.ok()) return fail(st);
  const std::filesystem::path data_dir = absl::GetFlag(FLAGS_data_dir);
  std::error_code ec;
  if (std::filesystem::exists(data_dir, ec) && !std::filesystem::is_directory(data_dir, ec))
    return usage("--data-dir " + data_dir.string() + ": a file, not a folder");
  absl::StatusOr<gaps::rpc::ServiceSecurity> security = gaps::rpc::service_security_from_flags();
  if (!security.ok()) return fail(security.status());
  auto worker_token = gaps::rpc::load_token(absl::GetFlag(FLAGS_worker_token_file), "GAPS_WORKER_TOKEN");
  if (!worker_token.ok()) return fail_reading(worker_token.status());

  gaps::TrainerServiceOptions options;
  options.data_dir = data_dir;
  options.job_store = absl::GetFlag(FLAGS_job_store);
  // The URI may hold a password: an environment variable keeps it off the command line (and out of `ps`).
  if (options.job_store.empty() && std::getenv("GAPS_JOB_STORE") != nullptr)
    options.job_store = std::getenv("GAPS_JOB_STORE");
  options.lease_seconds = absl::GetFlag(FLAGS_lease_seconds);
  options.replica_id = absl::GetFlag(FLAGS_replica_id);
  options.device = device;
  options.concurrency = absl::GetFlag(FLAGS_concurrency);
  options.max_crashes = absl::GetFlag(FLAGS_max_crashes);
  if (options.max_crashes < 1) return usage("--max-crashes must be at least 1");
  if (options.concurrency < 1) return usage("--concurrency must be at least 1");
  options.threads_per_job = absl::GetFlag(FLAGS_threads_per_job);
  if (options.threads_per_job < 0) return usage("--threads-per-job must be 0 (automatic) or positive");
  options.checkpoint_seconds = absl::GetFlag(FLAGS_checkpoint_seconds);
  if (!(options.checkpoint_seconds >= 0)) return usage("--checkpoint-seconds must be 0 or positive");
  options.token = security->settings.token;
  options.max_upload_bytes = absl::GetFlag(FLAGS_max_upload_mb) << 20;
  std::string lpips_note;
  absl::StatusOr<std::filesystem::path> lpips = lpips_weights(&lpips_note);
  if (!lpips.ok()) return fail(lpips.status());
  options.lpips_weights = *lpips;
  options.init_cache_dir = absl::GetFlag(FLAGS_init_cache);
  for (absl::string_view a : absl::StrSplit(absl::GetFlag(FLAGS_workers), ',', absl::SkipEmpty()))
    options.workers.addresses.emplace_back(a);
  options.workers.security = {*worker_token, absl::GetFlag(FLAGS_worker_tls_ca),
                              absl::GetFlag(FLAGS_worker_tls_server_name), absl::GetFlag(FLAGS_worker_tls_cert),
                              absl::GetFlag(FLAGS_worker_tls_key)};
  // The workers' TLS files, checked now rather than by the first job that needs a worker (which would fail, as
  // would every method job after it).
  if (!options.workers.security.tls_ca.empty() || !options.workers.security.tls_cert.empty()) {
    absl::StatusOr<std::shared_ptr<grpc::Channel>> probe =
        gaps::rpc::make_channel("127.0.0.1:1", options.workers.security);
    if (!probe.ok())
      return fail_reading(
          absl::Status(probe.status().code(), absl::StrCat("workers' TLS: ", probe.status().message())));
  }
  options.workers.generate_timeout = std::chrono::seconds(absl::GetFlag(FLAGS_worker_timeout_s));
  options.workers.max_rounds = absl::GetFlag(FLAGS_worker_rounds);
  const std::string encoding = absl::GetFlag(FLAGS_worker_encoding);
  if (encoding != "compact" && encoding != "float32")
    return usage("--worker-encoding " + encoding + ": one of compact, float32");
  options.workers.encoding =
      encoding == "compact" ? gaps::rpc::TensorEncoding::kUint8 : gaps::rpc::TensorEncoding::kFloat32;
  options.workers.shared_memory = absl::GetFlag(FLAGS_worker_shared_memory);
  options.workers.fan_out = absl::GetFlag(FLAGS_worker_fan_out);
  options.workers.share_adaptation = absl::GetFlag(FLAGS_worker_share_adaptation);
  const double grace = absl::GetFlag(FLAGS_worker_adaptation_grace_s);
  if (!(grace >= 0) || grace > 1e6) return usage("--worker-adaptation-grace-s must be in [0, 1e6] seconds");
  options.workers.adaptation_grace = std::chrono::milliseconds(static_cast<int64_t>(grace * 1000));
  // Regions a killed trainer on this host left behind in /dev/shm.
  gaps::rpc::remove_stale_regions();
  auto service = gaps::TrainerService::create(options);
  if (!service.ok()) return fail(service.status());

  absl::StatusOr<gaps::rpc::ListeningServer> server =
      gaps::rpc::start_server(absl::GetFlag(FLAGS_listen), *security, {service->get()});
  if (!server.ok()) return fail(server.status());
  if (auto st = (*service)->start(); !st.ok()) return fail(st);
  // One write per line: the job threads started above log to the same file.
  gaps::write_log_line(STDOUT_FILENO, absl::StrCat("gaps-trainer: serving on port ", server->port, " (device ", device,
                                                   ", ", options.workers.addresses.size(), " worker address(es))",
                                                   security->settings.tls_cert.empty() ? "" : " (TLS)",
                                                   security->settings.token.empty() ? "" : " (token required)", "; ",
                                                   lpips_note, "; trainer ", (*service)->replica_id(), ", job store ",
                                                   (*service)->store_description()));
  gaps::rpc::wait_for_stop_signal();
  gaps::write_log_line(
      STDOUT_FILENO,
      absl::StrCat("gaps-trainer: stopping; running jobs resume when a trainer starts on ", options.data_dir.string()));
  (*service)->shutdown();
  server->server->Shutdown(std::chrono::system_clock::now() + std::chrono::seconds(5));
  return 0;
}

}  // namespace

int main(int argc, char** argv) {
  return gaps::cli::run_main("gaps-trainer", [&] {
    if (const std::optional<int> done = gaps::cli::parse_program_command_line(argc, argv, command())) return *done;
    return serve();
  });
}

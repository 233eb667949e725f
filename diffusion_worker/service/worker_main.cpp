// gaps-worker: serves a pseudo-view generation backend over gRPC (gaps.v1.DiffusionWorker).
//   gaps-worker --listen 127.0.0.1:50052 --backend reproject [--backend-options JSON] [--token-file F]
//               [--tls-cert F --tls-key F [--tls-client-ca F]] [--queue-capacity N] [--max-batch N]
#include <unistd.h>
#include <algorithm>

#include <grpcpp/grpcpp.h>
#include <nlohmann/json.hpp>
#include "absl/flags/flag.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_join.h"
#include "common/cli/command_line.h"
#include "common/device.h"
#include "common/error_kind.h"
#include "common/io_util.h"
#include "diffusion_worker/backend_registry.h"
#include "diffusion_worker/service/worker_service.h"
#include "rpc/security.h"
#include "rpc/service_main.h"

ABSL_FLAG(std::string, listen, "127.0.0.1:50052", "address to serve on (a bare port binds 127.0.0.1)");
ABSL_FLAG(std::string, backend, "reproject", "generation backend");
ABSL_FLAG(std::string, backend_options, "", "JSON object of backend options");
ABSL_FLAG(std::string, device, "cpu", "device the backend runs on");
ABSL_FLAG(int, max_batch, 64, "most poses per Generate call");
ABSL_FLAG(int, queue_capacity, 4, "calls that may wait behind the running one before RESOURCE_EXHAUSTED");
ABSL_FLAG(uint64_t, max_request_mb, 1024, "largest accepted request in MiB");
ABSL_FLAG(int, max_scenes, 16,
          "scenes kept at most (their reference views and adaptations); past it the least recently used is "
          "forgotten and its trainer adapts this worker again");
ABSL_FLAG(bool, keep_scene_adaptations, true,
          "when jobs' scenes alternate on this worker, install what a scene's adaptation learnt (sdxl: its LoRA "
          "adapters) when the scene comes back; false: adapt it anew each time (LoRA training again)");
ABSL_FLAG(bool, shared_memory, true,
          "take payloads through shared memory from trainers on this host that share its /dev/shm (found out "
          "per trainer; others use the socket)");

namespace {

gaps::cli::CommandSpec command() {
  gaps::cli::CommandSpec spec;
  spec.name = "gaps-worker";
  spec.synopsis = "gaps-worker --listen ADDR --backend NAME [--backend-options JSON] [--device DEV] [flags]";
  spec.summary =
      "A diffusion worker: generates pseudo-views for a gaps-trainer's jobs with an in-process backend\n"
      "(reproject, or sdxl with its weights; see diffusion_worker/README.md). SIGTERM/SIGINT stop it.";
  spec.groups = {
      {"service",
       {"listen", "max_batch", "queue_capacity", "max_request_mb", "shared_memory", "keep_scene_adaptations",
        "max_scenes"}},
      {"backend", {"backend", "backend_options", "device", "gpu_memory_gib"}},
      {"security", gaps::rpc::security_flag_names()},
  };
  spec.epilogue = gaps::cli::exit_code_table();
  return spec;
}

int fail(const absl::Status& status) {
  gaps::write_log_line(STDERR_FILENO, absl::StrCat("gaps-worker: ", status.message()));
  return gaps::exit_code(status);
}

int usage(const std::string& message) { return fail(gaps::usage_error(message)); }

// The backend's name and device, checked before its weights are loaded.
absl::Status check_backend(const std::string& backend, const std::string& device) {
  const std::vector<std::string> known = gaps::known_generator_backends();
  if (std::find(known.begin(), known.end(), backend) == known.end())
    return gaps::usage_error(absl::StrCat("--backend ", backend, ": unknown; one of ", absl::StrJoin(known, ", ")));
  // A CPU backend only warns about a device it will not use, but the name must still be one.
  return gaps::generator_backend_uses_device(backend) ? gaps::check_device(device) : gaps::check_device_name(device);
}

// --device reaches a backend that computes on a device (sdxl, restore) as its "device" option. A CPU backend
// (reproject) gets nothing: the worker says at start-up that it computes on the CPU and reports "cpu".
std::string options_with_device(const std::string& backend, const std::string& options_json, const std::string& device,
                                std::string* error) {
  if (device == "cpu" || !gaps::generator_backend_uses_device(backend)) return options_json;
  nlohmann::json options =
      options_json.empty() ? nlohmann::json::object() : nlohmann::json::parse(options_json, nullptr, false);
  if (!options.is_object()) {
    *error = "--backend-options is not a JSON object";
    return "";
  }
  if (options.contains("device") && options["device"] != device) {
    *error = "--device " + device + " contradicts --backend-options' device " + options["device"].dump();
    return "";
  }
  options["device"] = device;
  return options.dump();
}

int serve() {
  const std::string backend = absl::GetFlag(FLAGS_backend);
  const std::string requested_device = absl::GetFlag(FLAGS_device);
  if (absl::Status st = check_backend(backend, requested_device); !st.ok()) return fail(st);
  const bool uses_device = gaps::generator_backend_uses_device(backend);
  if (!uses_device && requested_device != "cpu")
    gaps::write_log_line(STDERR_FILENO,
                         absl::StrCat("gaps-worker: the ", backend, " backend computes on the CPU; --device ",
                                      requested_device, " applies to device backends (sdxl, restore) only"));
  const std::string device = uses_device ? requested_device : "cpu";
  std::string error;
  const std::string backend_options =
      options_with_device(backend, absl::GetFlag(FLAGS_backend_options), requested_device, &error);
  if (!error.empty()) return usage(error);
  absl::StatusOr<gaps::rpc::ServiceSecurity> security = gaps::rpc::service_security_from_flags();
  if (!security.ok()) return fail(security.status());
  // Before the weights load: the cap must hold from the first allocation.
  if (absl::Status st = gaps::rpc::apply_gpu_memory_cap(device); !st.ok()) return fail(st);
  auto generator = gaps::make_generator(backend, backend_options);
  if (!generator.ok()) {
    // Option values are the user's to fix; otherwise the backend's files (weights) are at fault.
    const absl::Status& st = generator.status();
    const absl::Status located(st.code(),
                               (device == "cpu" ? "" : "--device " + device + ": ") + std::string(st.message()));
    return fail(absl::IsInvalidArgument(st) ? gaps::with_error_kind(located, gaps::ErrorKind::kUsage)
                                            : gaps::input_data_error(located));
  }

  gaps::WorkerServiceOptions options;
  options.backend = backend;
  options.device = device;
  options.max_batch = absl::GetFlag(FLAGS_max_batch);
  options.queue_capacity = absl::GetFlag(FLAGS_queue_capacity);
  options.shared_memory = absl::GetFlag(FLAGS_shared_memory);
  options.keep_scene_adaptations = absl::GetFlag(FLAGS_keep_scene_adaptations);
  options.max_scenes = absl::GetFlag(FLAGS_max_scenes);
  options.max_request_bytes = absl::GetFlag(FLAGS_max_request_mb) << 20;
  options.token = security->settings.token;
  if (options.max_batch <= 0 || options.queue_capacity < 0)
    return usage("--max-batch must be positive, --queue-capacity >= 0");
  if (options.max_scenes < 1) return usage("--max-scenes must be at least 1");
  gaps::WorkerService service(std::move(*generator), options);

  absl::StatusOr<gaps::rpc::ListeningServer> server =
      gaps::rpc::start_server(absl::GetFlag(FLAGS_listen), *security, {&service}, 4 << 20);
  if (!server.ok()) return fail(server.status());
  // The resolved port, so a caller that asked for port 0 learns which one it got.
  gaps::write_log_line(STDOUT_FILENO, absl::StrCat("gaps-worker: serving backend ", backend, " on port ", server->port,
                                                   security->settings.tls_cert.empty() ? "" : " (TLS)",
                                                   security->settings.token.empty() ? "" : " (token required)"));
  gaps::rpc::wait_for_stop_signal();
  server->server->Shutdown(std::chrono::system_clock::now() + std::chrono::seconds(5));
  return 0;
}

}  // namespace

int main(int argc, char** argv) {
  return gaps::cli::run_main("gaps-worker", [&] {
    if (const std::optional<int> done = gaps::cli::parse_program_command_line(argc, argv, command())) return *done;
    return serve();
  });
}

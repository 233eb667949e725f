// gaps-trainer: the training service (gaps.v1.Trainer) with its job queue and SQLite job store.
//   gaps-trainer --listen 127.0.0.1:50051 --workers 127.0.0.1:50052[,ADDR...] --data_dir DIR --device cpu|cuda:0
//                [--concurrency N] [--token_file F] [--tls_cert F --tls_key F [--tls_client_ca F]]
//                [--worker_token_file F] [--worker_tls_ca F [--worker_tls_cert F --worker_tls_key F]]
// SIGTERM/SIGINT: running jobs stop at their next iteration, write a checkpoint and stay RUNNING in the
// store; the next trainer started on the same data folder resumes them from it.
#include <atomic>
#include <csignal>
#include <cstdlib>
#include <iostream>
#include <thread>

#include <ATen/Context.h>
#include <grpcpp/grpcpp.h>
#include <grpcpp/health_check_service_interface.h>
#include "absl/flags/flag.h"
#include "absl/flags/parse.h"
#include "absl/flags/usage.h"
#include "absl/strings/str_split.h"
#include "rpc/security.h"
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
ABSL_FLAG(int, max_crashes, 2,
          "a job whose trainer died this many times while running it is FAILED at the next start instead of run again");
ABSL_FLAG(std::string, token_file, "", "file holding the bearer token callers must send (default: $GAPS_TOKEN)");
ABSL_FLAG(std::string, tls_cert, "", "PEM certificate chain; with --tls_key serves TLS");
ABSL_FLAG(std::string, tls_key, "", "PEM private key");
ABSL_FLAG(std::string, tls_client_ca, "",
          "CA certificate that must have signed every client's certificate (mutual TLS)");
ABSL_FLAG(std::string, worker_token_file, "",
          "token sent to the workers (default: $GAPS_WORKER_TOKEN, else none; the trainer's own token is never sent, "
          "so that whoever runs a worker address cannot drive the trainer)");
ABSL_FLAG(std::string, worker_tls_ca, "", "CA certificate of the workers' TLS (default: plaintext)");
ABSL_FLAG(std::string, worker_tls_server_name, "", "name the workers' certificates are checked against");
ABSL_FLAG(std::string, worker_tls_cert, "", "this trainer's client certificate, for workers that require one");
ABSL_FLAG(std::string, worker_tls_key, "", "private key of --worker_tls_cert");
ABSL_FLAG(int, worker_timeout_s, 300, "deadline of each generation call");
ABSL_FLAG(int, worker_rounds, 3, "passes over the worker pool (with backoff) before a phase is skipped");
ABSL_FLAG(uint64_t, max_upload_mb, 8192, "largest accepted scene upload in MiB");

namespace {

std::atomic<bool> g_stop{false};
void on_signal(int) { g_stop = true; }

int fail(const std::string& message) {
  std::cerr << "gaps-trainer: " << message << "\n";
  return 2;
}

}  // namespace

int main(int argc, char** argv) {
  absl::SetProgramUsageMessage("gaps-trainer --listen ADDR --workers ADDR[,ADDR...] --data_dir DIR --device DEV");
  absl::ParseCommandLine(argc, argv);
  const std::string device = absl::GetFlag(FLAGS_device);
  if (at::Device(device).is_cuda() && !at::hasCUDA()) return fail("--device " + device + ": no CUDA device available");
  auto token = gaps::rpc::load_token(absl::GetFlag(FLAGS_token_file));
  if (!token.ok()) return fail(std::string(token.status().message()));
  auto worker_token = gaps::rpc::load_token(absl::GetFlag(FLAGS_worker_token_file), "GAPS_WORKER_TOKEN");
  if (!worker_token.ok()) return fail(std::string(worker_token.status().message()));
  gaps::rpc::ServerSecurity security{*token, absl::GetFlag(FLAGS_tls_cert), absl::GetFlag(FLAGS_tls_key),
                                     absl::GetFlag(FLAGS_tls_client_ca)};
  auto credentials = gaps::rpc::server_credentials(security);
  if (!credentials.ok()) return fail(std::string(credentials.status().message()));

  gaps::TrainerServiceOptions options;
  options.data_dir = absl::GetFlag(FLAGS_data_dir);
  options.job_store = absl::GetFlag(FLAGS_job_store);
  // The URI may hold a password: an environment variable keeps it off the command line (and out of `ps`).
  if (options.job_store.empty() && std::getenv("GAPS_JOB_STORE") != nullptr)
    options.job_store = std::getenv("GAPS_JOB_STORE");
  options.lease_seconds = absl::GetFlag(FLAGS_lease_seconds);
  options.replica_id = absl::GetFlag(FLAGS_replica_id);
  options.device = device;
  options.concurrency = absl::GetFlag(FLAGS_concurrency);
  options.max_crashes = absl::GetFlag(FLAGS_max_crashes);
  if (options.max_crashes < 1) return fail("--max_crashes must be at least 1");
  options.token = *token;
  options.max_upload_bytes = absl::GetFlag(FLAGS_max_upload_mb) << 20;
  for (absl::string_view a : absl::StrSplit(absl::GetFlag(FLAGS_workers), ',', absl::SkipEmpty()))
    options.workers.addresses.emplace_back(a);
  options.workers.security = {*worker_token, absl::GetFlag(FLAGS_worker_tls_ca),
                              absl::GetFlag(FLAGS_worker_tls_server_name), absl::GetFlag(FLAGS_worker_tls_cert),
                              absl::GetFlag(FLAGS_worker_tls_key)};
  options.workers.generate_timeout = std::chrono::seconds(absl::GetFlag(FLAGS_worker_timeout_s));
  options.workers.max_rounds = absl::GetFlag(FLAGS_worker_rounds);
  auto service = gaps::TrainerService::create(options);
  if (!service.ok()) return fail(std::string(service.status().message()));

  grpc::EnableDefaultHealthCheckService(true);
  grpc::ServerBuilder builder;
  // gRPC would otherwise let a second server bind the same port and take a share of the calls.
  builder.AddChannelArgument(GRPC_ARG_ALLOW_REUSEPORT, 0);
  const std::string address = gaps::rpc::listen_address(absl::GetFlag(FLAGS_listen));
  int port = 0;
  builder.AddListeningPort(address, *credentials, &port);
  builder.RegisterService(service->get());
  std::unique_ptr<grpc::Server> server = builder.BuildAndStart();
  if (!server || port == 0)
    return fail("cannot listen on " + address +
                ": the address is in use or not local, or the TLS private key does not belong to the certificate");
  if (auto st = (*service)->start(); !st.ok()) return fail(std::string(st.message()));
  std::signal(SIGTERM, on_signal);
  std::signal(SIGINT, on_signal);
  std::cout << "gaps-trainer: serving on port " << port << " (device " << device << ", "
            << options.workers.addresses.size() << " worker address(es))" << (security.tls_cert.empty() ? "" : " (TLS)")
            << (security.token.empty() ? "" : " (token required)") << "; trainer " << (*service)->replica_id()
            << ", job store " << (*service)->store_description() << std::endl;
  while (!g_stop) std::this_thread::sleep_for(std::chrono::milliseconds(100));
  std::cout << "gaps-trainer: stopping; running jobs resume when a trainer starts on " << options.data_dir << std::endl;
  (*service)->shutdown();
  server->Shutdown(std::chrono::system_clock::now() + std::chrono::seconds(5));
  return 0;
}

#include "rpc/service_main.h"

#include <atomic>
#include <chrono>
#include <csignal>
#include <thread>

#include <grpcpp/grpcpp.h>
#include <grpcpp/health_check_service_interface.h>
#include "absl/flags/flag.h"
#include "common/device.h"
#include "common/error_kind.h"
#include "common/status_macros.h"

ABSL_FLAG(std::string, token_file, "", "file holding the bearer token callers must send (default: $GAPS_TOKEN)");
ABSL_FLAG(std::string, tls_cert, "", "PEM certificate chain; with --tls-key serves TLS");
ABSL_FLAG(std::string, tls_key, "", "PEM private key");
ABSL_FLAG(std::string, tls_client_ca, "",
          "CA certificate that must have signed every client's certificate (mutual TLS)");
ABSL_FLAG(double, gpu_memory_gib, 0,
          "most GiB this process's CUDA allocator may hold on --device (0: no cap); two processes sharing one card "
          "each take a share (docs/deploy.md: 24 GB cards)");

namespace gaps::rpc {
namespace {

std::atomic<bool> g_stop{false};
void on_signal(int) { g_stop = true; }

}  // namespace

std::vector<std::string> security_flag_names() { return {"token_file", "tls_cert", "tls_key", "tls_client_ca"}; }

absl::Status apply_gpu_memory_cap(const std::string& device) {
  return limit_device_memory(device, absl::GetFlag(FLAGS_gpu_memory_gib));
}

absl::StatusOr<ServiceSecurity> service_security_from_flags() {
  absl::StatusOr<std::string> token = load_token(absl::GetFlag(FLAGS_token_file));
  if (!token.ok()) return input_data_error(token.status());
  ServiceSecurity security;
  security.settings = {*token, absl::GetFlag(FLAGS_tls_cert), absl::GetFlag(FLAGS_tls_key),
                       absl::GetFlag(FLAGS_tls_client_ca)};
  absl::StatusOr<std::shared_ptr<grpc::ServerCredentials>> credentials = server_credentials(security.settings);
  if (!credentials.ok()) return input_data_error(credentials.status());
  security.credentials = std::move(*credentials);
  return security;
}

absl::StatusOr<ListeningServer> start_server(const std::string& address, const ServiceSecurity& security,
                                             const std::vector<grpc::Service*>& services, int max_receive_bytes) {
  grpc::EnableDefaultHealthCheckService(true);
  grpc::ServerBuilder builder;
  // gRPC would otherwise let a second server bind the same port and take a share of the calls.
  builder.AddChannelArgument(GRPC_ARG_ALLOW_REUSEPORT, 0);
  const std::string bound = listen_address(address);
  ListeningServer listening;
  builder.AddListeningPort(bound, security.credentials, &listening.port);
  for (grpc::Service* service : services) builder.RegisterService(service);
  if (max_receive_bytes >= 0) builder.SetMaxReceiveMessageSize(max_receive_bytes);
  listening.server = builder.BuildAndStart();
  if (!listening.server || listening.port == 0)
    return absl::FailedPreconditionError(
        "cannot listen on " + bound +
        ": the address is in use or not local, or the TLS private key does not belong to the certificate");
  return listening;
}

void wait_for_stop_signal() {
  std::signal(SIGTERM, on_signal);
  std::signal(SIGINT, on_signal);
  while (!g_stop) std::this_thread::sleep_for(std::chrono::milliseconds(100));
}

}  // namespace gaps::rpc

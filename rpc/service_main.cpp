#include "rpc/service_main.h"

#include <netdb.h>
#include <sys/socket.h>
#include <unistd.h>

#include <atomic>
#include <cerrno>
#include <chrono>
#include <csignal>
#include <cstring>
#include <memory>
#include <thread>

#include <grpcpp/grpcpp.h>
#include <grpcpp/health_check_service_interface.h>
#include "absl/flags/flag.h"
#include "absl/strings/numbers.h"
#include "absl/strings/str_cat.h"
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

// "HOST:PORT" or "[V6]:PORT" into its parts; false for any other form (left to gRPC to judge).
bool split_host_port(const std::string& address, std::string* host, std::string* port) {
  const size_t colon = address.rfind(':');
  if (colon == std::string::npos || colon == 0) return false;
  *host = address.substr(0, colon);
  *port = address.substr(colon + 1);
  if (host->size() >= 2 && host->front() == '[' && host->back() == ']') *host = host->substr(1, host->size() - 2);
  int number = 0;
  return absl::SimpleAtoi(*port, &number) && number > 0 && number <= 65535;
}

// Binds the address once before gRPC does, so that a port in use or an address that is not this machine's
// is said in those words (gRPC itself only logs a page of internal error text and fails). OK when the
// probe cannot tell; the server start then has the last word.
absl::Status probe_listen_address(const std::string& address) {
  std::string host, port;
  if (!split_host_port(address, &host, &port)) return absl::OkStatus();
  addrinfo hints{};
  hints.ai_family = AF_UNSPEC;
  hints.ai_socktype = SOCK_STREAM;
  hints.ai_flags = AI_PASSIVE | AI_NUMERICSERV;
  addrinfo* found = nullptr;
  if (const int rc = getaddrinfo(host.c_str(), port.c_str(), &hints, &found); rc != 0)
    return absl::InvalidArgumentError(absl::StrCat("cannot listen on ", address, ": ", gai_strerror(rc)));
  std::unique_ptr<addrinfo, decltype(&freeaddrinfo)> addresses(found, freeaddrinfo);
  const int fd = socket(found->ai_family, found->ai_socktype | SOCK_CLOEXEC, found->ai_protocol);
  if (fd < 0) return absl::OkStatus();
  const int yes = 1;
  setsockopt(fd, SOL_SOCKET, SO_REUSEADDR, &yes, sizeof yes);
  const int error = bind(fd, found->ai_addr, found->ai_addrlen) == 0 ? 0 : errno;
  close(fd);
  if (error == EADDRINUSE)
    return absl::FailedPreconditionError(absl::StrCat("cannot listen on ", address, ": port ", port,
                                                      " is in use by another program; choose another with --listen"));
  if (error == EADDRNOTAVAIL)
    return absl::FailedPreconditionError(
        absl::StrCat("cannot listen on ", address, ": ", host, " is not an address of this machine (see --listen)"));
  if (error != 0)
    return absl::FailedPreconditionError(absl::StrCat("cannot listen on ", address, ": ", std::strerror(error)));
  return absl::OkStatus();
}

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
  GAPS_RETURN_IF_ERROR(probe_listen_address(bound));
  ListeningServer listening;
  builder.AddListeningPort(bound, security.credentials, &listening.port);
  for (grpc::Service* service : services) builder.RegisterService(service);
  if (max_receive_bytes >= 0) builder.SetMaxReceiveMessageSize(max_receive_bytes);
  listening.server = builder.BuildAndStart();
  if (!listening.server || listening.port == 0)
    return absl::FailedPreconditionError(
        absl::StrCat("cannot listen on ", bound,
                     security.settings.tls_cert.empty() ? ": gRPC refused the address"
                                                        : ": gRPC refused the address or the TLS certificate and key"));
  return listening;
}

void wait_for_stop_signal() {
  std::signal(SIGTERM, on_signal);
  std::signal(SIGINT, on_signal);
  while (!g_stop) std::this_thread::sleep_for(std::chrono::milliseconds(100));
}

}  // namespace gaps::rpc

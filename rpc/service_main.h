#pragma once
// What the main functions of both services (gaps-trainer, gaps-worker) share: the flags of the bearer token
// and transport security, starting the gRPC server on its port, and waiting for SIGTERM/SIGINT. A library of
// its own (gaps_service_main) so that only the service programs carry these flags.
#include <memory>
#include <string>
#include <vector>

#include <grpcpp/security/server_credentials.h>
#include <grpcpp/server.h>
#include "absl/flags/declare.h"
#include "absl/status/statusor.h"
#include "rpc/security.h"

ABSL_DECLARE_FLAG(std::string, token_file);
ABSL_DECLARE_FLAG(std::string, tls_cert);
ABSL_DECLARE_FLAG(std::string, tls_key);
ABSL_DECLARE_FLAG(std::string, tls_client_ca);
ABSL_DECLARE_FLAG(double, gpu_memory_gib);

namespace gaps::rpc {

// The security flags' names, for a program's --help group.
std::vector<std::string> security_flag_names();

// --gpu-memory-gib on the service's device (common/device.h: limit_device_memory); 0 leaves it uncapped.
absl::Status apply_gpu_memory_cap(const std::string& device);

struct ServiceSecurity {
  ServerSecurity settings;
  std::shared_ptr<grpc::ServerCredentials> credentials;
};
// --token-file (or $GAPS_TOKEN) and the TLS files, read and checked (a key that does not belong to its
// certificate, an expired certificate): input data errors (common/error_kind.h) naming the file.
absl::StatusOr<ServiceSecurity> service_security_from_flags();

struct ListeningServer {
  std::unique_ptr<grpc::Server> server;
  int port = 0;  // the bound port (what a caller that asked for port 0 must learn)
};
// Starts a server with gRPC's health service on `address` (rpc::listen_address: a bare port binds
// 127.0.0.1); one process per port. max_receive_bytes < 0 keeps gRPC's limit.
absl::StatusOr<ListeningServer> start_server(const std::string& address, const ServiceSecurity& security,
                                             const std::vector<grpc::Service*>& services, int max_receive_bytes = -1);

// Blocks until the process gets SIGTERM or SIGINT.
void wait_for_stop_signal();

}  // namespace gaps::rpc

#pragma once
// Transport security and bearer-token authentication shared by the services and their clients.
// Without TLS files the channel is plaintext (the services then bind 127.0.0.1 by default); without a
// token every caller is accepted.
#include <memory>
#include <string>

#include <grpcpp/grpcpp.h>
#include "absl/status/statusor.h"

namespace gaps::rpc {

struct ServerSecurity {
  std::string token;     // required bearer token ("authorization: Bearer <token>"); empty: none
  std::string tls_cert;  // PEM certificate chain file; with tls_key enables TLS
  std::string tls_key;   // PEM private key file
  // PEM file of the CA that signs client certificates; when set (with TLS), a client must present a
  // certificate it signed (mutual TLS), else the handshake fails.
  std::string tls_client_ca;
};

struct ClientSecurity {
  std::string token;   // bearer token sent with every call; empty: none
  std::string tls_ca;  // PEM file of the CA that signed the server's certificate; enables TLS
  // Name the certificate is checked against when it differs from the address' host (e.g. "localhost").
  std::string tls_server_name;
  // This client's certificate chain and private key (PEM files), for servers that require one.
  std::string tls_cert;
  std::string tls_key;
};

absl::StatusOr<std::shared_ptr<grpc::ServerCredentials>> server_credentials(const ServerSecurity& security);
absl::StatusOr<std::shared_ptr<grpc::Channel>> make_channel(const std::string& address, const ClientSecurity& security);

// OK when the call carries the server's token (or none is required); UNAUTHENTICATED otherwise.
grpc::Status check_token(const grpc::ServerContext& context, const std::string& token);
// Adds the token (when set) to an outgoing call.
void attach_token(grpc::ClientContext& context, const std::string& token);

// The token from a file (first line, whitespace trimmed) when `file` is set, else from the environment
// variable `env_variable` (GAPS_TOKEN; the trainer reads its workers' token from GAPS_WORKER_TOKEN), else
// empty.
absl::StatusOr<std::string> load_token(const std::string& file, const char* env_variable = "GAPS_TOKEN");

// Addresses without a host (":50051" or "50051") bind 127.0.0.1; anything else is used as given.
std::string listen_address(const std::string& address);

}  // namespace gaps::rpc

#include "rpc/security.h"

#include <cstdlib>
#include <memory>

#include <openssl/bio.h>
#include <openssl/err.h>
#include <openssl/evp.h>
#include <openssl/pem.h>
#include <openssl/x509.h>

#include "absl/strings/ascii.h"
#include "absl/strings/match.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/strip.h"
#include "common/error_kind.h"
#include "common/io_util.h"
#include "common/status_macros.h"

namespace gaps::rpc {
namespace {

// gRPC takes any bytes here and fails later with messages that name neither the file nor the problem
// ("empty address list", "cannot listen"), so the PEM block a file must hold is checked as it is read.
absl::StatusOr<std::string> read_pem(const std::string& path, const std::string& what) {
  GAPS_ASSIGN_OR_RETURN(std::string pem, read_file_bytes(path, what));
  const bool key = absl::StrContains(what, "private key");
  const bool has_block = key ? absl::StrContains(pem, "-----BEGIN") && absl::StrContains(pem, "PRIVATE KEY-----")
                             : absl::StrContains(pem, "-----BEGIN CERTIFICATE-----");
  if (!has_block)
    return absl::InvalidArgumentError(absl::StrCat(path, ": not a PEM ", key ? "private key" : "certificate", " (the ",
                                                   what, " must hold a '-----BEGIN ",
                                                   key ? "... PRIVATE KEY" : "CERTIFICATE", "-----' block)"));
  return pem;
}

std::string openssl_error() {
  const unsigned long code = ERR_get_error();
  ERR_clear_error();
  if (code == 0) return "no detail";
  char text[256];
  ERR_error_string_n(code, text, sizeof(text));
  return text;
}

// gRPC reports a key that does not belong to its certificate, or one it cannot parse, only as a server
// that "cannot listen" (or a handshake that fails later), so the pair is checked here, naming the files.
absl::Status check_key_pair(const std::string& cert_pem, const std::string& cert_path, const std::string& key_pem,
                            const std::string& key_path) {
  const auto bio = [](const std::string& pem) {
    return std::unique_ptr<BIO, decltype(&BIO_free)>(BIO_new_mem_buf(pem.data(), static_cast<int>(pem.size())),
                                                     &BIO_free);
  };
  auto cert_bio = bio(cert_pem), key_bio = bio(key_pem);
  std::unique_ptr<X509, decltype(&X509_free)> cert(PEM_read_bio_X509(cert_bio.get(), nullptr, nullptr, nullptr),
                                                   &X509_free);
  if (!cert)
    return absl::InvalidArgumentError(
        absl::StrCat(cert_path, ": the certificate cannot be read (", openssl_error(), ")"));
  std::unique_ptr<EVP_PKEY, decltype(&EVP_PKEY_free)> key(
      PEM_read_bio_PrivateKey(key_bio.get(), nullptr, nullptr, nullptr), &EVP_PKEY_free);
  if (!key)
    return absl::InvalidArgumentError(absl::StrCat(key_path, ": the private key cannot be read (", openssl_error(),
                                                   "; an encrypted key is not supported)"));
  if (X509_check_private_key(cert.get(), key.get()) != 1) {
    ERR_clear_error();
    return absl::InvalidArgumentError(absl::StrCat("the TLS private key ", key_path,
                                                   " does not belong to the certificate ", cert_path,
                                                   " (their public keys differ)"));
  }
  if (X509_cmp_current_time(X509_get0_notAfter(cert.get())) < 0)
    return absl::InvalidArgumentError(absl::StrCat(cert_path, ": the certificate has expired"));
  return absl::OkStatus();
}

// Same duration whatever the first differing byte, so the token cannot be guessed byte by byte (its
// length may leak; tokens should be long random strings).
bool equal_constant_time(const std::string& a, const std::string& b) {
  if (a.size() != b.size()) return false;
  unsigned char diff = 0;
  for (size_t i = 0; i < a.size(); ++i) diff |= static_cast<unsigned char>(a[i] ^ b[i]);
  return diff == 0;
}

}  // namespace

absl::StatusOr<std::shared_ptr<grpc::ServerCredentials>> server_credentials(const ServerSecurity& s) {
  if (s.tls_cert.empty() != s.tls_key.empty()) return usage_error("TLS needs both a certificate and a private key");
  if (s.tls_cert.empty() && !s.tls_client_ca.empty())
    return usage_error("a client CA (mutual TLS) needs the server's own TLS certificate and key");
  if (s.tls_cert.empty()) return grpc::InsecureServerCredentials();
  grpc::SslServerCredentialsOptions options;
  if (!s.tls_client_ca.empty()) {
    GAPS_ASSIGN_OR_RETURN(options.pem_root_certs, read_pem(s.tls_client_ca, "TLS client CA certificate"));
    options.client_certificate_request = GRPC_SSL_REQUEST_AND_REQUIRE_CLIENT_CERTIFICATE_AND_VERIFY;
  }
  grpc::SslServerCredentialsOptions::PemKeyCertPair pair;
  GAPS_ASSIGN_OR_RETURN(pair.cert_chain, read_pem(s.tls_cert, "TLS certificate"));
  GAPS_ASSIGN_OR_RETURN(pair.private_key, read_pem(s.tls_key, "TLS private key"));
  GAPS_RETURN_IF_ERROR(check_key_pair(pair.cert_chain, s.tls_cert, pair.private_key, s.tls_key));
  options.pem_key_cert_pairs.push_back(std::move(pair));
  return grpc::SslServerCredentials(options);
}

absl::StatusOr<std::shared_ptr<grpc::Channel>> make_channel(const std::string& address, const ClientSecurity& s) {
  grpc::ChannelArguments args;
  args.SetMaxReceiveMessageSize(16 << 20);
  if (s.tls_cert.empty() != s.tls_key.empty())
    return usage_error("a client TLS certificate needs its private key, and the other way round");
  if (s.tls_ca.empty() && !s.tls_cert.empty())
    return usage_error("a client TLS certificate needs the server's CA certificate (TLS)");
  if (s.tls_ca.empty()) return grpc::CreateCustomChannel(address, grpc::InsecureChannelCredentials(), args);
  grpc::SslCredentialsOptions options;
  GAPS_ASSIGN_OR_RETURN(options.pem_root_certs, read_pem(s.tls_ca, "TLS CA certificate"));
  if (!s.tls_cert.empty()) {
    GAPS_ASSIGN_OR_RETURN(options.pem_cert_chain, read_pem(s.tls_cert, "TLS client certificate"));
    GAPS_ASSIGN_OR_RETURN(options.pem_private_key, read_pem(s.tls_key, "TLS client private key"));
    GAPS_RETURN_IF_ERROR(check_key_pair(options.pem_cert_chain, s.tls_cert, options.pem_private_key, s.tls_key));
  }
  if (!s.tls_server_name.empty()) args.SetSslTargetNameOverride(s.tls_server_name);
  return grpc::CreateCustomChannel(address, grpc::SslCredentials(options), args);
}

grpc::Status check_token(const grpc::ServerContext& context, const std::string& token) {
  if (token.empty()) return grpc::Status::OK;
  const auto& metadata = context.client_metadata();
  const auto it = metadata.find("authorization");
  if (it == metadata.end()) return grpc::Status(grpc::StatusCode::UNAUTHENTICATED, "missing bearer token");
  const std::string value(it->second.data(), it->second.size());
  constexpr char kPrefix[] = "Bearer ";
  if (value.rfind(kPrefix, 0) != 0 || !equal_constant_time(value.substr(sizeof(kPrefix) - 1), token))
    return grpc::Status(grpc::StatusCode::UNAUTHENTICATED, "invalid bearer token");
  return grpc::Status::OK;
}

void attach_token(grpc::ClientContext& context, const std::string& token) {
  if (!token.empty()) context.AddMetadata("authorization", "Bearer " + token);
}

absl::StatusOr<std::string> load_token(const std::string& file, const char* env_variable) {
  if (!file.empty()) {
    GAPS_ASSIGN_OR_RETURN(std::string text, read_file_bytes(file, "token file"));
    const size_t newline = text.find('\n');
    std::string token(absl::StripAsciiWhitespace(text.substr(0, newline)));
    if (token.empty()) return absl::InvalidArgumentError(absl::StrCat(file, ": token file is empty"));
    return token;
  }
  const char* env = std::getenv(env_variable);
  return env ? std::string(env) : std::string();
}

std::string listen_address(const std::string& address) {
  if (address.find(':') == std::string::npos) return absl::StrCat("127.0.0.1:", address);
  if (address[0] == ':') return absl::StrCat("127.0.0.1", address);
  return address;
}

}  // namespace gaps::rpc

#include "rpc/transport_check.h"

#include <netdb.h>
#include <sys/socket.h>
#include <sys/time.h>
#include <unistd.h>

#include <cerrno>
#include <memory>
#include <optional>
#include <vector>

#include <openssl/err.h>
#include <openssl/ssl.h>
#include <openssl/x509v3.h>

#include "absl/strings/match.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_join.h"

namespace gaps::rpc {
namespace {

struct Endpoint {
  std::string host;
  std::string port;
};

// host:port, [v6]:port, with gRPC's dns:/// or ipv4: scheme; nothing for other target forms.
std::optional<Endpoint> endpoint_of(std::string address) {
  for (const char* scheme : {"dns:///", "ipv4:", "ipv6:"})
    if (absl::StartsWith(address, scheme)) address = address.substr(std::string(scheme).size());
  if (!address.empty() && address[0] == '[') {
    const size_t close = address.find("]:");
    if (close == std::string::npos) return std::nullopt;
    return Endpoint{address.substr(1, close - 1), address.substr(close + 2)};
  }
  const size_t colon = address.rfind(':');
  if (colon == std::string::npos || colon == 0) return std::nullopt;
  return Endpoint{address.substr(0, colon), address.substr(colon + 1)};
}

class Socket {
 public:
  explicit Socket(int fd) : fd_(fd) {}
  ~Socket() {
    if (fd_ >= 0) close(fd_);
  }
  Socket(const Socket&) = delete;
  int fd() const { return fd_; }

 private:
  int fd_;
};

// A TCP connection whose connect, reads and writes give up after `timeout`; -1 when none is made.
int connect_tcp(const Endpoint& e, std::chrono::milliseconds timeout) {
  addrinfo hints{};
  hints.ai_socktype = SOCK_STREAM;
  addrinfo* found = nullptr;
  if (getaddrinfo(e.host.c_str(), e.port.c_str(), &hints, &found) != 0) return -1;
  const std::unique_ptr<addrinfo, decltype(&freeaddrinfo)> list(found, &freeaddrinfo);
  timeval tv{static_cast<time_t>(timeout.count() / 1000), static_cast<suseconds_t>(timeout.count() % 1000 * 1000)};
  for (const addrinfo* a = found; a != nullptr; a = a->ai_next) {
    const int fd = socket(a->ai_family, a->ai_socktype, a->ai_protocol);
    if (fd < 0) continue;
    setsockopt(fd, SOL_SOCKET, SO_RCVTIMEO, &tv, sizeof(tv));
    setsockopt(fd, SOL_SOCKET, SO_SNDTIMEO, &tv, sizeof(tv));
    if (connect(fd, a->ai_addr, a->ai_addrlen) == 0) return fd;
    close(fd);
  }
  return -1;
}

using Context = std::unique_ptr<SSL_CTX, decltype(&SSL_CTX_free)>;
using Connection = std::unique_ptr<SSL, decltype(&SSL_free)>;

// What the handshake (and first read) met.
struct Outcome {
  bool handshake_done = false;
  bool answered = false;  // the server sent an HTTP/2 frame after the handshake
  bool hung_up = false;   // it closed the connection after the handshake instead
  long verify_result = X509_V_OK;
  int reason = 0;  // OpenSSL's reason of the first error; alerts from the server are SSL_AD_REASON_OFFSET + alert
};

bool is_alert(int reason) { return reason > SSL_AD_REASON_OFFSET && reason < SSL_AD_REASON_OFFSET + 256; }

bool refuses_client_certificate(int reason) {
  switch (reason - SSL_AD_REASON_OFFSET) {
    case SSL_AD_HANDSHAKE_FAILURE:
    case SSL_AD_BAD_CERTIFICATE:
    case SSL_AD_UNSUPPORTED_CERTIFICATE:
    case SSL_AD_CERTIFICATE_REVOKED:
    case SSL_AD_CERTIFICATE_EXPIRED:
    case SSL_AD_CERTIFICATE_UNKNOWN:
    case SSL_AD_UNKNOWN_CA:
    case SSL_AD_DECRYPT_ERROR:
    case SSL_AD_CERTIFICATE_REQUIRED:
      return true;
    default:
      return false;
  }
}

int first_error_reason() {
  const unsigned long code = ERR_peek_error();
  ERR_clear_error();
  return code == 0 ? 0 : ERR_GET_REASON(code);
}

// The names the server's certificate holds (subjectAltName DNS and IP entries, else its CN), kept by the
// verify callback: after a failed verification the handshake offers no certificate to ask.
thread_local std::vector<std::string> t_certificate_names;

std::vector<std::string> names_in(X509* cert) {
  std::vector<std::string> names;
  auto* alt = static_cast<GENERAL_NAMES*>(X509_get_ext_d2i(cert, NID_subject_alt_name, nullptr, nullptr));
  for (int i = 0; alt != nullptr && i < sk_GENERAL_NAME_num(alt); ++i) {
    const GENERAL_NAME* name = sk_GENERAL_NAME_value(alt, i);
    if (name->type == GEN_DNS)
      names.emplace_back(reinterpret_cast<const char*>(ASN1_STRING_get0_data(name->d.dNSName)),
                         ASN1_STRING_length(name->d.dNSName));
    if (name->type == GEN_IPADD && ASN1_STRING_length(name->d.iPAddress) == 4) {
      const unsigned char* ip = ASN1_STRING_get0_data(name->d.iPAddress);
      names.push_back(absl::StrCat(ip[0], ".", ip[1], ".", ip[2], ".", ip[3]));
    }
  }
  GENERAL_NAMES_free(alt);
  if (names.empty()) {
    char cn[256] = {};
    if (X509_NAME_get_text_by_NID(X509_get_subject_name(cert), NID_commonName, cn, sizeof(cn)) > 0)
      names.emplace_back(cn);
  }
  return names;
}

int remember_certificate_names(int ok, X509_STORE_CTX* store) {
  if (X509_STORE_CTX_get_error_depth(store) == 0)
    if (X509* cert = X509_STORE_CTX_get_current_cert(store)) t_certificate_names = names_in(cert);
  return ok;
}

Context client_context(const ClientSecurity& s, bool verify) {
  Context ctx(SSL_CTX_new(TLS_client_method()), &SSL_CTX_free);
  if (!ctx) return ctx;
  static const unsigned char kAlpn[] = {2, 'h', '2'};  // gRPC servers speak HTTP/2 only
  SSL_CTX_set_alpn_protos(ctx.get(), kAlpn, sizeof(kAlpn));
  if (!verify) return ctx;
  SSL_CTX_set_verify(ctx.get(), SSL_VERIFY_PEER, remember_certificate_names);
  SSL_CTX_load_verify_locations(ctx.get(), s.tls_ca.c_str(), nullptr);
  if (!s.tls_cert.empty()) {
    SSL_CTX_use_certificate_chain_file(ctx.get(), s.tls_cert.c_str());
    SSL_CTX_use_PrivateKey_file(ctx.get(), s.tls_key.c_str(), SSL_FILETYPE_PEM);
  }
  ERR_clear_error();
  return ctx;
}

// The handshake on `fd` checking the certificate for `name` (when verify), then the server's first frame read:
// TLS 1.3 servers refuse a client certificate only after the handshake.
Outcome handshake(int fd, const ClientSecurity& s, const std::string& name, bool verify) {
  Outcome out;
  const Context ctx = client_context(s, verify);
  if (!ctx) return out;
  const Connection ssl(SSL_new(ctx.get()), &SSL_free);
  SSL_set_fd(ssl.get(), fd);
  SSL_set_tlsext_host_name(ssl.get(), name.c_str());
  if (verify) SSL_set1_host(ssl.get(), name.c_str());
  t_certificate_names.clear();
  ERR_clear_error();
  if (SSL_connect(ssl.get()) != 1) {
    out.verify_result = SSL_get_verify_result(ssl.get());
    out.reason = first_error_reason();
    return out;
  }
  out.handshake_done = true;
  // An HTTP/2 server sends its SETTINGS first, unasked; a refusal comes instead as an alert. Nothing is
  // written, so a server that has hung up cannot raise SIGPIPE here.
  char frame[64];
  errno = 0;
  if (const int read = SSL_read(ssl.get(), frame, sizeof(frame)); read <= 0) {
    const int error = SSL_get_error(ssl.get(), read);
    const bool timed_out = error == SSL_ERROR_SYSCALL && (errno == EAGAIN || errno == EWOULDBLOCK);
    out.reason = first_error_reason();
    out.hung_up = !timed_out;
    return out;
  }
  out.answered = true;
  return out;
}

std::string certificate_problem(const Outcome& o, const ClientSecurity& s, const std::string& name) {
  if (o.verify_result == X509_V_ERR_HOSTNAME_MISMATCH || o.verify_result == X509_V_ERR_IP_ADDRESS_MISMATCH) {
    const std::string held = absl::StrJoin(t_certificate_names, ", ");
    return absl::StrCat("the trainer's certificate is for ", held.empty() ? "other names" : held, ", not for ", name,
                        ": give --tls-server-name ", t_certificate_names.empty() ? "NAME" : t_certificate_names.front(),
                        " (a name the certificate holds), or connect by that name");
  }
  if (o.verify_result == X509_V_ERR_CERT_HAS_EXPIRED)
    return "the trainer's certificate has expired: the trainer needs a new one";
  return absl::StrCat("the trainer's certificate is not trusted by --tls-ca ", s.tls_ca, " (",
                      X509_verify_cert_error_string(o.verify_result),
                      "): give the CA certificate that signed the trainer's --tls-cert");
}

std::string client_certificate_problem(const ClientSecurity& s) {
  if (s.tls_cert.empty())
    return "the trainer requires a client certificate (mutual TLS): give --tls-client-cert and --tls-client-key, "
           "signed by the CA of its --tls-client-ca";
  return absl::StrCat("the trainer refused the client certificate ", s.tls_cert,
                      ": it must be signed by the CA of the trainer's --tls-client-ca, for client use, and valid now");
}

std::string diagnose_tls_client(int fd, const ClientSecurity& s, const Endpoint& e) {
  const std::string name = s.tls_server_name.empty() ? e.host : s.tls_server_name;
  const Outcome o = handshake(fd, s, name, /*verify=*/true);
  if (o.verify_result != X509_V_OK) return certificate_problem(o, s, name);
  // The alert of a refusal may be lost when the server resets the connection; a server that hangs up on a
  // finished handshake without a word has refused the client all the same.
  if (refuses_client_certificate(o.reason) || (o.hung_up && !is_alert(o.reason))) return client_certificate_problem(s);
  if (!o.handshake_done && !is_alert(o.reason))
    return "the trainer speaks plaintext, not TLS: leave out --tls-ca (and the other --tls-* flags), or start "
           "gaps-trainer with --tls-cert and --tls-key";
  return "";
}

std::string diagnose_plaintext_client(int fd, const ClientSecurity& s, const Endpoint& e) {
  const Outcome o = handshake(fd, s, e.host, /*verify=*/false);
  // A plaintext server answers a ClientHello with no TLS at all; a TLS one completes it or sends an alert.
  if (o.handshake_done || is_alert(o.reason))
    return "the trainer requires TLS and this client spoke plaintext: give --tls-ca with the CA certificate that "
           "signed the trainer's certificate (and --tls-server-name when it names another host)";
  return "";
}

}  // namespace

std::string diagnose_transport(const std::string& address, const ClientSecurity& security,
                               std::chrono::milliseconds timeout) {
  const std::optional<Endpoint> e = endpoint_of(address);
  if (!e) return "";
  const Socket connection(connect_tcp(*e, timeout));
  if (connection.fd() < 0) return "";
  return security.tls_ca.empty() ? diagnose_plaintext_client(connection.fd(), security, *e)
                                 : diagnose_tls_client(connection.fd(), security, *e);
}

}  // namespace gaps::rpc

#pragma once
// Why a channel to a service does not come up although something listens at its address. gRPC reports every
// TLS failure alike (the channel only turns TRANSIENT_FAILURE), so the server is met again directly, with
// OpenSSL, as the channel meets it: a TCP connection, then the TLS handshake (or, for a plaintext client, a
// handshake that only asks whether the server speaks TLS), and for TLS a first read, where TLS 1.3 servers
// refuse a client certificate.
#include <chrono>
#include <string>

#include "rpc/security.h"

namespace gaps::rpc {

// One sentence saying what is wrong and what to do: the CA of `security.tls_ca` did not sign the server's
// certificate; the certificate is not for the name the client checks; the server speaks TLS and the client
// plaintext, or the other way round; the server requires a client certificate, or refused the one given.
// "" when nothing answers at `address` (host:port) within `timeout`, or the probe finds none of these.
std::string diagnose_transport(const std::string& address, const ClientSecurity& security,
                               std::chrono::milliseconds timeout);

}  // namespace gaps::rpc

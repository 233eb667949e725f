#include "client/view_server.h"

#include <netdb.h>
#include <poll.h>
#include <sys/socket.h>
#include <sys/time.h>
#include <unistd.h>

#include <cerrno>
#include <cstring>
#include <vector>

#include "absl/strings/match.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_split.h"
#include "common/error_kind.h"
#include "common/io_util.h"

namespace gaps::client {
namespace {

constexpr size_t kMaxRequestHead = 16 * 1024;
constexpr int kIoTimeoutSeconds = 10;  // a client that stalls cannot hold the (sequential) server longer

std::string response(int code, const std::string& reason, const std::string& content_type, const std::string& body,
                     bool head_only, const std::string& extra_headers = "") {
  return absl::StrCat("HTTP/1.1 ", code, " ", reason, "\r\nContent-Type: ", content_type,
                      "\r\nContent-Length: ", body.size(), "\r\nCache-Control: no-store\r\n", extra_headers,
                      "Connection: close\r\n\r\n", head_only ? "" : body);
}

std::string error_response(int code, const std::string& reason, const std::string& detail, bool head_only = false,
                           const std::string& extra_headers = "") {
  return response(code, reason, "text/plain; charset=utf-8", absl::StrCat(code, " ", reason, ": ", detail, "\n"),
                  head_only, extra_headers);
}

// Reads the request head (up to the blank line); empty when the client sent nothing usable.
std::string read_request_head(int connection) {
  std::string head;
  char buffer[4096];
  while (head.find("\r\n\r\n") == std::string::npos && head.size() <= kMaxRequestHead) {
    const ssize_t n = recv(connection, buffer, sizeof buffer, 0);
    if (n < 0 && errno == EINTR) continue;
    if (n <= 0) break;
    head.append(buffer, static_cast<size_t>(n));
  }
  return head;
}

void send_all(int connection, const std::string& bytes) {
  size_t sent = 0;
  while (sent < bytes.size()) {
    const ssize_t n = send(connection, bytes.data() + sent, bytes.size() - sent, MSG_NOSIGNAL);
    if (n < 0 && errno == EINTR) continue;
    if (n <= 0) return;  // the client went away
    sent += static_cast<size_t>(n);
  }
}

std::string display_host(const std::string& host) {
  return host.find(':') != std::string::npos ? absl::StrCat("[", host, "]") : host;
}

}  // namespace

std::string http_response(const viewer::WebSite& site, const std::string& request) {
  const size_t line_end = request.find("\r\n");
  if (line_end == std::string::npos) return error_response(400, "Bad Request", "no request line");
  const std::vector<std::string> parts = absl::StrSplit(request.substr(0, line_end), ' ');
  if (parts.size() != 3 || parts[1].empty() || parts[1][0] != '/' || !absl::StartsWith(parts[2], "HTTP/1."))
    return error_response(400, "Bad Request", "expected 'GET /path HTTP/1.1'");
  const std::string& method = parts[0];
  const bool head_only = method == "HEAD";
  if (method != "GET" && !head_only)
    return error_response(405, "Method Not Allowed", method + " (only GET and HEAD)", false, "Allow: GET, HEAD\r\n");
  const std::string path = parts[1].substr(0, parts[1].find_first_of("?#"));
  const auto it = site.find(path);
  if (it == site.end()) return error_response(404, "Not Found", path, head_only);
  const viewer::WebResource& resource = it->second;
  if (resource.file.empty()) return response(200, "OK", resource.content_type, resource.body, head_only);
  const absl::StatusOr<std::string> bytes = read_file_bytes(resource.file);
  if (!bytes.ok()) return error_response(404, "Not Found", path, head_only);
  return response(200, "OK", resource.content_type, *bytes, head_only);
}

absl::StatusOr<std::unique_ptr<ViewServer>> ViewServer::start(const std::string& host, int port, viewer::WebSite site) {
  if (port < 0 || port > 65535) return usage_error(absl::StrCat("--port ", port, ": not a port (0 to 65535)"));
  addrinfo hints{};
  hints.ai_family = AF_UNSPEC;
  hints.ai_socktype = SOCK_STREAM;
  hints.ai_flags = AI_PASSIVE | AI_NUMERICSERV;
  addrinfo* found = nullptr;
  if (const int rc = getaddrinfo(host.c_str(), std::to_string(port).c_str(), &hints, &found); rc != 0)
    return usage_error(absl::StrCat("--host ", host, ": ", gai_strerror(rc)));
  std::unique_ptr<addrinfo, decltype(&freeaddrinfo)> addresses(found, freeaddrinfo);
  const int fd = socket(found->ai_family, found->ai_socktype | SOCK_CLOEXEC, found->ai_protocol);
  if (fd < 0) return absl::InternalError(absl::StrCat("socket: ", std::strerror(errno)));
  const int yes = 1;
  setsockopt(fd, SOL_SOCKET, SO_REUSEADDR, &yes, sizeof yes);
  if (bind(fd, found->ai_addr, found->ai_addrlen) != 0 || listen(fd, 16) != 0) {
    const int error = errno;
    close(fd);
    if (error == EADDRINUSE)
      return usage_error(absl::StrCat("port ", port, " on ", host,
                                      " is in use; choose another with --port (--port 0 picks a free one)"));
    return usage_error(absl::StrCat("cannot listen on ", display_host(host), ":", port, ": ", std::strerror(error),
                                    " (see --host, --port)"));
  }
  sockaddr_storage bound{};
  socklen_t length = sizeof bound;
  getsockname(fd, reinterpret_cast<sockaddr*>(&bound), &length);
  const int actual = ntohs(bound.ss_family == AF_INET6 ? reinterpret_cast<sockaddr_in6*>(&bound)->sin6_port
                                                       : reinterpret_cast<sockaddr_in*>(&bound)->sin_port);
  return std::unique_ptr<ViewServer>(new ViewServer(fd, host, actual, std::move(site)));
}

ViewServer::ViewServer(int socket, std::string host, int port, viewer::WebSite site)
    : socket_(socket), host_(std::move(host)), port_(port), site_(std::move(site)) {}

ViewServer::~ViewServer() { close(socket_); }

std::string ViewServer::url() const { return absl::StrCat("http://", display_host(host_), ":", port_, "/"); }

void ViewServer::serve(const std::function<bool()>& should_stop) {
  while (!should_stop()) {
    pollfd p{socket_, POLLIN, 0};
    if (poll(&p, 1, 200) <= 0 || !(p.revents & POLLIN)) continue;
    const int connection = accept4(socket_, nullptr, nullptr, SOCK_CLOEXEC);
    if (connection < 0) continue;
    answer(connection);
    close(connection);
  }
}

void ViewServer::answer(int connection) const {
  const timeval timeout{kIoTimeoutSeconds, 0};
  setsockopt(connection, SOL_SOCKET, SO_RCVTIMEO, &timeout, sizeof timeout);
  setsockopt(connection, SOL_SOCKET, SO_SNDTIMEO, &timeout, sizeof timeout);
  const std::string head = read_request_head(connection);
  if (head.empty()) return;
  if (head.find("\r\n\r\n") == std::string::npos) {
    send_all(connection,
             error_response(head.size() > kMaxRequestHead ? 431 : 400,
                            head.size() > kMaxRequestHead ? "Request Header Fields Too Large" : "Bad Request",
                            "incomplete request head"));
    return;
  }
  send_all(connection, http_response(site_, head));
}

}  // namespace gaps::client

#pragma once
// The HTTP/1.1 server of `gaps view`: GET and HEAD of a fixed set of resources (gs_trainer/viewer/site.h) on
// POSIX sockets, one connection at a time, each closed after its response. Nothing else is served: a path
// outside the set is 404, whatever it contains, so nothing of the file system is reachable through it.
#include <functional>
#include <memory>
#include <string>

#include "absl/status/statusor.h"
#include "gs_trainer/viewer/site.h"

namespace gaps::client {

class ViewServer {
 public:
  // Listens on host:port (port 0: the system picks a free one). A busy port or an address this machine does
  // not have is a usage error naming it and --port/--host.
  static absl::StatusOr<std::unique_ptr<ViewServer>> start(const std::string& host, int port, viewer::WebSite site);
  ~ViewServer();
  ViewServer(const ViewServer&) = delete;
  ViewServer& operator=(const ViewServer&) = delete;

  int port() const { return port_; }
  // http://HOST:PORT/ (an IPv6 host in brackets).
  std::string url() const;
  // Answers requests until `should_stop` returns true; it is asked at least every 200 ms.
  void serve(const std::function<bool()>& should_stop);

 private:
  ViewServer(int socket, std::string host, int port, viewer::WebSite site);
  void answer(int connection) const;

  int socket_;
  std::string host_;
  int port_;
  viewer::WebSite site_;
};

// The complete response (status line, headers, body) to the request head `request` (request line and
// headers). Exposed for tests.
std::string http_response(const viewer::WebSite& site, const std::string& request);

}  // namespace gaps::client

#pragma once
// A private PostgreSQL server for tests: a fresh cluster (initdb) in a temporary folder, on a free loopback
// port with trust authentication and fsync off, stopped and removed with the object. PostgreSQL refuses to
// run as root, so as root the server runs as the `postgres` user (Debian's package creates it), else as
// `nobody`. Missing binaries are an error naming the package, not a skip: scripts/setup.sh installs them.
#include <netinet/in.h>
#include <pwd.h>
#include <sys/socket.h>
#include <unistd.h>

#include <cstdlib>
#include <filesystem>
#include <memory>
#include <string>

#include "absl/status/statusor.h"
#include "absl/strings/str_cat.h"
#include "common/io_util.h"

namespace gaps::test {

class PostgresServer {
 public:
  static absl::StatusOr<std::unique_ptr<PostgresServer>> start(const std::filesystem::path& dir) {
    namespace fs = std::filesystem;
    const std::string bin = binaries();
    if (bin.empty())
      return absl::FailedPreconditionError(
          "PostgreSQL's initdb and pg_ctl were not found (install Debian's postgresql package: scripts/setup.sh)");
    std::unique_ptr<PostgresServer> server(new PostgresServer(dir / "pgdata", bin));
    fs::create_directories(server->data_);
    std::string as;  // the command prefix that drops root
    if (geteuid() == 0) {
      const passwd* user = getpwnam("postgres");
      if (user == nullptr) user = getpwnam("nobody");
      if (user == nullptr) return absl::FailedPreconditionError("running as root, but no postgres or nobody user");
      if (chown(server->data_.c_str(), user->pw_uid, user->pw_gid) != 0)
        return absl::InternalError("cannot hand the PostgreSQL data folder to " + std::string(user->pw_name));
      as = absl::StrCat("runuser -u ", user->pw_name, " -- ");
    }
    server->prefix_ = as;
    server->port_ = free_port();
    const std::string log = (server->data_ / "server.log").string();
    if (!server->run(absl::StrCat(bin, "/initdb -D ", server->data_.string(),
                                  " -U postgres --auth=trust -E UTF8 > /dev/null 2>&1")))
      return absl::InternalError("initdb failed in " + server->data_.string());
    if (!server->run(
            absl::StrCat(bin, "/pg_ctl -D ", server->data_.string(), " -l ", log, " -w -t 60 -o \"-p ", server->port_,
                         " -k ", server->data_.string(),
                         " -c listen_addresses=127.0.0.1 -c fsync=off -c max_connections=200\" start > /dev/null")))
      return absl::InternalError(absl::StrCat("pg_ctl start failed; its log: ", read_file_bytes(log).value_or("")));
    server->started_ = true;
    return server;
  }

  ~PostgresServer() {
    if (started_) run(absl::StrCat(bin_, "/pg_ctl -D ", data_.string(), " -m immediate stop > /dev/null 2>&1"));
    remove_tree(data_);
  }

  int port() const { return port_; }
  std::string uri(const std::string& database = "postgres") const {
    return absl::StrCat("postgresql://postgres@127.0.0.1:", port_, "/", database);
  }
  // A fresh database for one test.
  absl::Status create_database(const std::string& name) {
    if (!run(absl::StrCat("psql -q -h 127.0.0.1 -p ", port_, " -U postgres -c 'CREATE DATABASE ", name,
                          "' postgres > /dev/null")))
      return absl::InternalError("CREATE DATABASE " + name + " failed");
    return absl::OkStatus();
  }

 private:
  PostgresServer(std::filesystem::path data, std::string bin) : data_(std::move(data)), bin_(std::move(bin)) {}

  bool run(const std::string& command) const { return std::system((prefix_ + command).c_str()) == 0; }

  static std::string binaries() {
    namespace fs = std::filesystem;
    for (const char* version : {"17", "16", "15", "14", "13"}) {
      const std::string dir = absl::StrCat("/usr/lib/postgresql/", version, "/bin");
      if (fs::exists(dir + "/initdb") && fs::exists(dir + "/pg_ctl")) return dir;
    }
    return "";
  }

  static int free_port() {
    const int fd = socket(AF_INET, SOCK_STREAM, 0);
    sockaddr_in address{};
    address.sin_family = AF_INET;
    address.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
    socklen_t length = sizeof(address);
    bind(fd, reinterpret_cast<sockaddr*>(&address), sizeof(address));
    getsockname(fd, reinterpret_cast<sockaddr*>(&address), &length);
    close(fd);
    return ntohs(address.sin_port);
  }

  std::filesystem::path data_;
  std::string bin_;
  std::string prefix_;
  int port_ = 0;
  bool started_ = false;
};

}  // namespace gaps::test

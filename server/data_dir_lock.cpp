#include "server/data_dir_lock.h"

#include <fcntl.h>
#include <sys/file.h>
#include <unistd.h>

#include <cerrno>
#include <cstring>
#include <string>

#include "absl/strings/str_cat.h"

namespace gaps {

absl::StatusOr<std::unique_ptr<DataDirLock>> DataDirLock::acquire(const std::filesystem::path& data_dir, bool shared) {
  const std::filesystem::path path = data_dir / "trainer.lock";
  const int fd = ::open(path.c_str(), O_RDWR | O_CREAT | O_CLOEXEC, 0644);
  if (fd < 0) return absl::PermissionDeniedError(absl::StrCat(path.string(), ": ", std::strerror(errno)));
  if (::flock(fd, (shared ? LOCK_SH : LOCK_EX) | LOCK_NB) != 0) {
    const int error = errno;
    char holder[32] = {0};
    const ssize_t n = ::pread(fd, holder, sizeof(holder) - 1, 0);
    ::close(fd);
    if (error == EWOULDBLOCK && shared)
      return absl::FailedPreconditionError(absl::StrCat(
          data_dir.string(), " is in use by a gaps-trainer with its own SQLite job store",
          n > 0 ? absl::StrCat(" (pid ", holder, ")") : "", "; replicas sharing a folder need a shared --job_store"));
    if (error == EWOULDBLOCK)
      return absl::FailedPreconditionError(absl::StrCat(
          data_dir.string(), " is in use by another gaps-trainer", n > 0 ? absl::StrCat(" (pid ", holder, ")") : "",
          "; give each trainer its own --data_dir, or share the folder through a PostgreSQL --job_store"));
    return absl::InternalError(absl::StrCat(path.string(), ": cannot lock: ", std::strerror(error)));
  }
  if (shared) return std::unique_ptr<DataDirLock>(new DataDirLock(fd));  // the holders are many: no pid
  const std::string pid = std::to_string(::getpid());
  if (::ftruncate(fd, 0) != 0 || ::pwrite(fd, pid.data(), pid.size(), 0) != static_cast<ssize_t>(pid.size())) {
    ::close(fd);
    return absl::InternalError(absl::StrCat(path.string(), ": cannot record the pid: ", std::strerror(errno)));
  }
  return std::unique_ptr<DataDirLock>(new DataDirLock(fd));
}

DataDirLock::~DataDirLock() { ::close(fd_); }

}  // namespace gaps

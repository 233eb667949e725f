#include "common/io_util.h"

#include <unistd.h>

#include <cerrno>
#include <cstring>
#include <thread>

#include <fstream>
#include <iterator>
#include <system_error>

#include "absl/strings/str_cat.h"

namespace gaps {

absl::StatusOr<std::string> read_file_bytes(const std::filesystem::path& path, absl::string_view what) {
  std::error_code ec;
  if (!std::filesystem::exists(path, ec))
    return absl::NotFoundError(absl::StrCat(path.string(), ": ", what, " not found"));
  if (!std::filesystem::is_regular_file(path, ec))
    return absl::InvalidArgumentError(absl::StrCat(path.string(), ": not a regular file"));
  std::ifstream in(path, std::ios::binary);
  if (!in) return absl::PermissionDeniedError(absl::StrCat(path.string(), ": cannot be opened"));
  std::string bytes{std::istreambuf_iterator<char>(in), std::istreambuf_iterator<char>()};
  if (in.bad()) return absl::DataLossError(absl::StrCat(path.string(), ": read error"));
  return bytes;
}

absl::Status write_file_atomically(const std::filesystem::path& path, const std::function<void(std::ostream&)>& write) {
  std::filesystem::path partial = path;
  partial += absl::StrCat(".partial-", ::getpid(), "-", std::hash<std::thread::id>{}(std::this_thread::get_id()));
  errno = 0;
  std::ofstream out(partial, std::ios::binary | std::ios::trunc);
  if (out) write(out);
  if (out) out.flush();
  out.close();
  const int error = errno;
  std::error_code ec;
  if (!out) {
    std::filesystem::remove(partial, ec);
    const bool full = error == ENOSPC || error == EDQUOT;
    const std::string why = full ? "the disk is full" : error != 0 ? std::strerror(error) : "write failed";
    return full ? absl::ResourceExhaustedError(absl::StrCat(path.string(), ": cannot be written (", why, ")"))
                : absl::PermissionDeniedError(absl::StrCat(path.string(), ": cannot be written (", why, ")"));
  }
  std::filesystem::rename(partial, path, ec);
  if (ec) {
    std::filesystem::remove(partial, ec);
    return absl::PermissionDeniedError(absl::StrCat(path.string(), ": cannot be written (", ec.message(), ")"));
  }
  return absl::OkStatus();
}

absl::Status write_file_bytes(const std::filesystem::path& path, absl::string_view bytes) {
  return write_file_atomically(
      path, [&](std::ostream& out) { out.write(bytes.data(), static_cast<std::streamsize>(bytes.size())); });
}

void remove_tree(const std::filesystem::path& dir) {
  std::error_code ec;
  if (!std::filesystem::is_directory(dir, ec)) return;
  for (const auto& entry : std::filesystem::directory_iterator(dir, ec)) {
    if (entry.is_directory(ec)) remove_tree(entry.path());
    std::filesystem::remove(entry.path(), ec);
  }
  std::filesystem::remove(dir, ec);
}

uint64_t fnv1a(const void* data, size_t size) {
  uint64_t hash = 1469598103934665603ull;
  for (size_t i = 0; i < size; ++i) hash = (hash ^ static_cast<const unsigned char*>(data)[i]) * 1099511628211ull;
  return hash;
}

void write_log_line(int fd, absl::string_view line) {
  const std::string text = absl::StrCat(line, "\n");
  size_t done = 0;
  while (done < text.size()) {
    const ssize_t n = ::write(fd, text.data() + done, text.size() - done);
    if (n < 0 && errno == EINTR) continue;
    if (n <= 0) return;  // a log that cannot be written is not worth failing the service for
    done += static_cast<size_t>(n);
  }
}

}  // namespace gaps

#include "rpc/shared_memory.h"

#include <fcntl.h>
#include <signal.h>
#include <sys/mman.h>
#include <sys/stat.h>
#include <unistd.h>

#include <atomic>
#include <cerrno>
#include <cstring>
#include <filesystem>
#include <random>

#include "absl/strings/match.h"
#include "absl/strings/numbers.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_split.h"

namespace gaps::rpc {
namespace {

constexpr char kRegionPrefix[] = "/gaps-region-";
constexpr char kProbePrefix[] = "/gaps-probe-";
constexpr uint64_t kAlignment = 64;

std::string errno_text() { return std::strerror(errno); }

// "<prefix><digits>-<digits>": the only names this module creates, so the only ones it opens.
bool well_formed(const std::string& name, const std::string& prefix) {
  if (!absl::StartsWith(name, prefix)) return false;
  const std::vector<std::string> parts = absl::StrSplit(name.substr(prefix.size()), '-');
  if (parts.size() != 2) return false;
  for (const std::string& part : parts) {
    if (part.empty() || part.size() > 20) return false;
    for (char c : part)
      if (c < '0' || c > '9') return false;
  }
  return true;
}

absl::StatusOr<uint8_t*> map(int fd, uint64_t size, const std::string& name) {
  if (size == 0) return absl::InvalidArgumentError(absl::StrCat("shared memory ", name, ": empty region"));
  void* p = mmap(nullptr, size, PROT_READ | PROT_WRITE, MAP_SHARED, fd, 0);
  if (p == MAP_FAILED) return absl::InternalError(absl::StrCat("shared memory ", name, ": mmap: ", errno_text()));
  return static_cast<uint8_t*>(p);
}

uint64_t random_u64() {
  static thread_local std::mt19937_64 rng(std::random_device{}());
  return rng();
}

}  // namespace

absl::StatusOr<std::unique_ptr<SharedRegion>> SharedRegion::create(uint64_t size) {
  static std::atomic<uint64_t> counter{0};
  const std::string name = absl::StrCat(kRegionPrefix, getpid(), "-", counter++);
  const int fd = shm_open(name.c_str(), O_CREAT | O_EXCL | O_RDWR, 0600);
  if (fd < 0) return absl::UnavailableError(absl::StrCat("shared memory ", name, ": shm_open: ", errno_text()));
  if (ftruncate(fd, static_cast<off_t>(size)) != 0) {
    const std::string why = errno_text();
    close(fd);
    shm_unlink(name.c_str());
    return absl::ResourceExhaustedError(
        absl::StrCat("shared memory ", name, ": cannot size to ", size, " bytes: ", why));
  }
  absl::StatusOr<uint8_t*> data = map(fd, size, name);
  close(fd);
  if (!data.ok()) {
    shm_unlink(name.c_str());
    return data.status();
  }
  return std::unique_ptr<SharedRegion>(new SharedRegion(name, *data, size, true));
}

absl::StatusOr<std::unique_ptr<SharedRegion>> SharedRegion::open(const std::string& name, uint64_t size) {
  if (!well_formed(name, kRegionPrefix))
    return absl::InvalidArgumentError(
        absl::StrCat("shared memory region name '", name, "' is not one a gaps trainer creates"));
  const int fd = shm_open(name.c_str(), O_RDWR, 0);
  if (fd < 0)
    return absl::FailedPreconditionError(
        absl::StrCat("shared memory ", name, ": ", errno_text(), " (the caller does not share this host's /dev/shm)"));
  struct stat st {};
  if (fstat(fd, &st) != 0 || static_cast<uint64_t>(st.st_size) != size) {
    close(fd);
    return absl::InvalidArgumentError(
        absl::StrCat("shared memory ", name, ": holds ", st.st_size, " bytes, the request says ", size));
  }
  absl::StatusOr<uint8_t*> data = map(fd, size, name);
  close(fd);
  if (!data.ok()) return data.status();
  return std::unique_ptr<SharedRegion>(new SharedRegion(name, *data, size, false));
}

SharedRegion::~SharedRegion() {
  munmap(data_, size_);
  if (owner_) shm_unlink(name_.c_str());
}

absl::Status SharedRegion::check_slice(uint64_t offset, uint64_t length, const std::string& what) const {
  if (offset > size_ || length > size_ - offset)
    return absl::InvalidArgumentError(absl::StrCat(what, ": bytes [", offset, ", ", offset, " + ", length,
                                                   ") lie outside the shared region of ", size_, " bytes"));
  return absl::OkStatus();
}

uint64_t arena_bytes(uint64_t length) { return (length + kAlignment - 1) / kAlignment * kAlignment; }

absl::StatusOr<uint64_t> SharedArena::allocate(uint64_t length) {
  const uint64_t need = arena_bytes(length);
  if (next_ > region_.size() || need > region_.size() - next_)
    return absl::ResourceExhaustedError(absl::StrCat("shared region ", region_.name(), " of ", region_.size(),
                                                     " bytes has no room for ", length, " more"));
  const uint64_t offset = next_;
  next_ += need;
  return offset;
}

absl::StatusOr<std::unique_ptr<SharedMemoryProbe>> SharedMemoryProbe::create() {
  const std::string name = absl::StrCat(kProbePrefix, getpid(), "-", random_u64() % 1000000000000ULL);
  const std::string token = absl::StrCat(random_u64(), random_u64());
  const int fd = shm_open(name.c_str(), O_CREAT | O_EXCL | O_RDWR, 0644);
  if (fd < 0) return absl::UnavailableError(absl::StrCat("shared memory probe ", name, ": ", errno_text()));
  const bool written = write(fd, token.data(), token.size()) == static_cast<ssize_t>(token.size());
  close(fd);
  if (!written) {
    shm_unlink(name.c_str());
    return absl::UnavailableError(absl::StrCat("shared memory probe ", name, ": cannot write the token"));
  }
  return std::unique_ptr<SharedMemoryProbe>(new SharedMemoryProbe(name, token));
}

SharedMemoryProbe::~SharedMemoryProbe() { shm_unlink(name_.c_str()); }

bool shares_memory_with(const std::string& name, const std::string& token) {
  if (!well_formed(name, kProbePrefix) || token.empty() || token.size() > 64) return false;
  const int fd = shm_open(name.c_str(), O_RDONLY, 0);
  if (fd < 0) return false;
  char buffer[65] = {0};
  const ssize_t n = read(fd, buffer, sizeof(buffer) - 1);
  close(fd);
  return n == static_cast<ssize_t>(token.size()) && token == std::string(buffer, n);
}

int remove_stale_regions() {
  int removed = 0;
  std::error_code ec;
  for (const auto& entry : std::filesystem::directory_iterator("/dev/shm", ec)) {
    const std::string name = "/" + entry.path().filename().string();
    const char* prefix = well_formed(name, kRegionPrefix)  ? kRegionPrefix
                         : well_formed(name, kProbePrefix) ? kProbePrefix
                                                           : nullptr;
    if (prefix == nullptr) continue;
    const std::vector<std::string> parts = absl::StrSplit(name.substr(std::strlen(prefix)), '-');
    int pid = 0;
    if (!absl::SimpleAtoi(parts[0], &pid) || pid <= 0) continue;
    if (kill(pid, 0) == 0 || errno != ESRCH) continue;  // alive, or not ours to judge
    removed += shm_unlink(name.c_str()) == 0;
  }
  return removed;
}

}  // namespace gaps::rpc

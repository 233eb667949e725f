#pragma once
// Shared memory between a trainer and a worker on one host. The bulk of a Generate call (renders, reference
// images, the answer's images) is written into a POSIX shared-memory object instead of the message; the message
// carries where each tensor lies (Tensor.shared). Whether two processes share a shared-memory namespace (the
// same host and container, or a /dev/shm mounted into both) is found out, not assumed: a worker creates a
// probe object holding a random token and names both in GetInfo; a trainer that reads the same token there
// may pass payloads through shared memory, any other stays on the socket.
#include <cstdint>
#include <memory>
#include <string>

#include "absl/status/statusor.h"

namespace gaps::rpc {

// A POSIX shared-memory object mapped read-write.
class SharedRegion {
 public:
  // A new object of `size` bytes named /gaps-region-<pid>-<n>; unlinked when this object is destroyed.
  static absl::StatusOr<std::unique_ptr<SharedRegion>> create(uint64_t size);
  // Maps an object another process created with create(); refuses other names (a caller must not make a
  // worker open arbitrary objects) and an object whose size is not `size`.
  static absl::StatusOr<std::unique_ptr<SharedRegion>> open(const std::string& name, uint64_t size);
  ~SharedRegion();
  SharedRegion(const SharedRegion&) = delete;
  SharedRegion& operator=(const SharedRegion&) = delete;

  const std::string& name() const { return name_; }
  uint64_t size() const { return size_; }
  uint8_t* data() { return data_; }
  const uint8_t* data() const { return data_; }
  // OK when [offset, offset + length) lies within the region, else INVALID_ARGUMENT naming `what`.
  absl::Status check_slice(uint64_t offset, uint64_t length, const std::string& what) const;

 private:
  SharedRegion(std::string name, uint8_t* data, uint64_t size, bool owner)
      : name_(std::move(name)), data_(data), size_(size), owner_(owner) {}
  std::string name_;
  uint8_t* data_;
  uint64_t size_;
  bool owner_;  // created here: unlinked at destruction
};

// Consecutive 64-byte-aligned slices of a region, from `begin` on.
class SharedArena {
 public:
  explicit SharedArena(SharedRegion& region, uint64_t begin = 0) : region_(region), next_(begin) {}
  // The offset of `length` fresh bytes, or RESOURCE_EXHAUSTED when the region is full.
  absl::StatusOr<uint64_t> allocate(uint64_t length);
  SharedRegion& region() { return region_; }
  uint64_t used_end() const { return next_; }

 private:
  SharedRegion& region_;
  uint64_t next_;
};

// Bytes an arena needs for slices of these lengths (alignment included).
uint64_t arena_bytes(uint64_t length);

// The worker's half of the negotiation: a shared-memory object /gaps-probe-<pid>-<random> holding a random
// token, unlinked when this object is destroyed.
class SharedMemoryProbe {
 public:
  static absl::StatusOr<std::unique_ptr<SharedMemoryProbe>> create();
  ~SharedMemoryProbe();
  const std::string& name() const { return name_; }
  const std::string& token() const { return token_; }

 private:
  SharedMemoryProbe(std::string name, std::string token) : name_(std::move(name)), token_(std::move(token)) {}
  std::string name_, token_;
};

// The trainer's half: true when the probe object `name` exists here and holds `token`.
bool shares_memory_with(const std::string& name, const std::string& token);

// Unlinks /gaps-region-<pid>-* and /gaps-probe-<pid>-* objects whose creating process is gone (a trainer or
// worker that was killed leaves them behind; a trainer cleans up at start). Returns how many it removed.
int remove_stale_regions();

}  // namespace gaps::rpc

#pragma once
// Whole-file reads and writes whose errors name the file, shared by the scene and image readers, a
// folder removal that is safe in programs linking LibTorch, and the content hash of cache file names.
#include <cstddef>
#include <cstdint>
#include <filesystem>
#include <functional>
#include <ostream>
#include <string>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "absl/strings/string_view.h"

namespace gaps {

// NotFound when the file is missing; `what` describes it in that message ("image file", "poses file", ...).
absl::StatusOr<std::string> read_file_bytes(const std::filesystem::path& path, absl::string_view what = "file");
// Both write a temporary file beside `path` and rename it into place only once everything was written, so that a
// reader (a fetch, a listing of artifacts) never sees a partial file and a failure leaves none behind. The error
// names the file and why (a full disk says so).
absl::Status write_file_bytes(const std::filesystem::path& path, absl::string_view bytes);
absl::Status write_file_atomically(const std::filesystem::path& path, const std::function<void(std::ostream&)>& write);

// Removes a folder and everything below it, one entry at a time, ignoring what cannot be removed:
// std::filesystem::remove_all must not be called where libtorch.so (which exports its own copy) is
// loaded, as that copy crashes.
void remove_tree(const std::filesystem::path& dir);

// FNV-1a, 64 bit: a fingerprint that is the same in every process and build (cache file names; std::hash
// promises neither).
uint64_t fnv1a(const void* data, size_t size);
inline uint64_t fnv1a(absl::string_view text) { return fnv1a(text.data(), text.size()); }

// Writes `line` and a newline to the file descriptor in one write(2), so that lines logged by a service's
// threads (and its stdout and stderr sharing one log file) never interleave mid-line, as `<<` chains can.
void write_log_line(int fd, absl::string_view line);

}  // namespace gaps

#pragma once
// Whole-file reads and writes whose errors name the file, shared by the scene and image readers, and a
// folder removal that is safe in programs linking LibTorch.
#include <filesystem>
#include <string>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "absl/strings/string_view.h"

namespace gaps {

// NotFound when the file is missing; `what` describes it in that message ("image file", "poses file", ...).
absl::StatusOr<std::string> read_file_bytes(const std::filesystem::path& path, absl::string_view what = "file");
absl::Status write_file_bytes(const std::filesystem::path& path, absl::string_view bytes);

// Removes a folder and everything below it, one entry at a time, ignoring what cannot be removed:
// std::filesystem::remove_all must not be called where libtorch.so (which exports its own copy) is
// loaded, as that copy crashes.
void remove_tree(const std::filesystem::path& dir);

}  // namespace gaps

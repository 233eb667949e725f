#pragma once
// Whole-file reads and writes whose errors name the file, shared by the scene and image readers.
#include <filesystem>
#include <string>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "absl/strings/string_view.h"

namespace gaps {

// NotFound when the file is missing; `what` describes it in that message ("image file", "poses file", ...).
absl::StatusOr<std::string> read_file_bytes(const std::filesystem::path& path, absl::string_view what = "file");
absl::Status write_file_bytes(const std::filesystem::path& path, absl::string_view bytes);

}  // namespace gaps

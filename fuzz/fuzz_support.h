#pragma once
// What the fuzz targets share. Parsers that read files (as users hand them files) get the input through a
// scratch folder private to the process; scenes get small valid images beside the fuzzed pose files.
#include <cstddef>
#include <cstdint>
#include <filesystem>
#include <string>
#include "absl/strings/string_view.h"

namespace gaps::fuzz {

inline absl::string_view as_bytes(const uint8_t* data, size_t size) {
  return {reinterpret_cast<const char*>(data), size};
}

// A folder private to this process, created on first use and removed at exit.
const std::filesystem::path& scratch_dir();
// Writes `bytes` to scratch_dir()/name (replacing it) and returns its path.
std::filesystem::path write_scratch(const std::string& name, absl::string_view bytes);
// scratch_dir()/name with images/000.png, 001.png, ... (`count` valid PNGs of width x height), made once.
std::filesystem::path scene_with_images(const std::string& name, int count, int width, int height);

}  // namespace gaps::fuzz

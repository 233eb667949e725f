#pragma once
// The folder gaps keeps what it makes once and reuses (the venv, initial point clouds, the LPIPS weights):
// $GAPS_CACHE, else ~/.cache/gaps, as scripts/setup.sh uses it; empty when neither variable is set.
#include <cstdlib>
#include <filesystem>

namespace gaps {

inline std::filesystem::path gaps_cache_dir() {
  if (const char* dir = std::getenv("GAPS_CACHE"); dir != nullptr && *dir != '\0') return dir;
  if (const char* home = std::getenv("HOME"); home != nullptr && *home != '\0')
    return std::filesystem::path(home) / ".cache" / "gaps";
  return {};
}

}  // namespace gaps

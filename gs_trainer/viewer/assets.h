#pragma once
// The page's files (assets/: index.html, viewer.css and the scripts), built into the binary: CMake writes
// them into a generated source (embed_assets.cmake), so `gaps view` and report.html need no files at run time.
#include <string>
#include <vector>

namespace gaps::viewer {

struct Asset {
  std::string name;  // file name under assets/, e.g. "viewer.js"
  std::string text;
};

const std::vector<Asset>& viewer_assets();

}  // namespace gaps::viewer

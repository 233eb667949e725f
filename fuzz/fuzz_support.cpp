#include "fuzz/fuzz_support.h"

#include <cstdlib>
#include <iostream>

#include <ATen/ATen.h>
#include "absl/strings/str_format.h"
#include "common/image_io.h"
#include "common/io_util.h"

namespace gaps::fuzz {
namespace {

namespace fs = std::filesystem;

fs::path make_scratch_dir() {
  std::string pattern = (fs::temp_directory_path() / "gaps-fuzz-XXXXXX").string();
  if (mkdtemp(pattern.data()) == nullptr) {
    std::cerr << "fuzz: cannot create a scratch folder under " << fs::temp_directory_path() << "\n";
    std::abort();
  }
  std::atexit([] { remove_tree(scratch_dir()); });
  return pattern;
}

void must(const absl::Status& status) {
  if (status.ok()) return;
  std::cerr << "fuzz: setting up the scratch folder failed: " << status << "\n";
  std::abort();
}

}  // namespace

const fs::path& scratch_dir() {
  static const fs::path dir = make_scratch_dir();
  return dir;
}

fs::path write_scratch(const std::string& name, absl::string_view bytes) {
  const fs::path path = scratch_dir() / name;
  must(write_file_bytes(path, bytes));
  return path;
}

fs::path scene_with_images(const std::string& name, int count, int width, int height) {
  const fs::path root = scratch_dir() / name;
  if (fs::exists(root / "images")) return root;
  fs::create_directories(root / "images");
  for (int i = 0; i < count; ++i)
    must(write_png(root / "images" / absl::StrFormat("%03d.png", i),
                   at::full({height, width, 3}, 0.1 * (i + 1), at::kFloat)));
  return root;
}

}  // namespace gaps::fuzz

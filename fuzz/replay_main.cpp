// The fuzz targets without libFuzzer: every file named on the command line, and every file below the
// folders named, goes through LLVMFuzzerTestOneInput once, so the seed corpora and the inputs that once
// broke a parser run in the ordinary test suite with any compiler.
#include <algorithm>
#include <cstdint>
#include <filesystem>
#include <iostream>
#include <vector>

#include "common/io_util.h"

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size);

int main(int argc, char** argv) {
  namespace fs = std::filesystem;
  std::vector<fs::path> inputs;
  for (int i = 1; i < argc; ++i) {
    const fs::path arg(argv[i]);
    if (fs::is_directory(arg)) {
      for (const auto& entry : fs::recursive_directory_iterator(arg))
        if (entry.is_regular_file()) inputs.push_back(entry.path());
    } else if (fs::is_regular_file(arg)) {
      inputs.push_back(arg);
    } else {
      std::cerr << argv[0] << ": " << arg << " is neither a file nor a folder\n";
      return 2;
    }
  }
  if (inputs.empty()) {
    std::cerr << argv[0] << ": no inputs to replay (name corpus files or folders)\n";
    return 2;
  }
  std::sort(inputs.begin(), inputs.end());
  for (const auto& input : inputs) {
    const auto bytes = gaps::read_file_bytes(input, "fuzz input");
    if (!bytes.ok()) {
      std::cerr << bytes.status() << "\n";
      return 2;
    }
    std::cout << "replaying " << input.filename().string() << " (" << bytes->size() << " bytes)\n";
    LLVMFuzzerTestOneInput(reinterpret_cast<const uint8_t*>(bytes->data()), bytes->size());
  }
  std::cout << "replayed " << inputs.size() << " inputs\n";
  return 0;
}

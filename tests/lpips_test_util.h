#pragma once
// LPIPS parity fixtures, shared by lpips_test.cpp and its CUDA test in gpu/: tests/scripts/lpips_reference.py
// (run with GAPS_PYTHON once per test process) writes a random VGG16 backbone, torch pickles and image pairs
// scored by PyPI's `lpips`, and a manifest naming them.
#include <unistd.h>

#include <algorithm>
#include <cstdlib>
#include <cstring>
#include <fstream>
#include <iterator>
#include <string>
#include <utility>

#include <ATen/ATen.h>
#include <gtest/gtest.h>
#include <nlohmann/json.hpp>
#include "common/io_util.h"
#include "gs_trainer/eval/lpips.h"
#include "tests/test_util.h"

namespace gaps::test {

// The LPIPS v0.1 linear weights come with the benchmark data (GAPS_DATA_DIR), which is never committed.
inline const std::string kLinWeights = std::string(GAPS_DATA_DIR) + "/lpips/vgg.pth";

// Exit status of tests/scripts/lpips_reference.py when a Python module it needs is missing.
constexpr int kMissingPythonModule = 77;

inline std::string make_temp_dir(const std::string& stem) {
  std::string pattern = "/tmp/" + stem + "_XXXXXX";
  return mkdtemp(pattern.data()) != nullptr ? pattern : std::string();
}

inline std::string read_file(const std::string& path) {
  std::ifstream in(path, std::ios::binary);
  return std::string(std::istreambuf_iterator<char>(in), {});
}

// The script's outputs, made once per test process (test suite); every test skips when the linear weights
// or the script's Python modules are missing, and fails when the script does.
class PythonFixtures : public ::testing::Test {
 protected:
  static void SetUpTestSuite() {
    error_.clear();
    skip_.clear();
    if (access(kLinWeights.c_str(), R_OK) != 0) {
      skip_ = kLinWeights + " is missing (benchmark data not found at GAPS_DATA_DIR)";
      return;
    }
    if (access(GAPS_PYTHON, X_OK) != 0) {
      error_ = std::string("GAPS_PYTHON (") + GAPS_PYTHON +
               ") is not an executable; run scripts/setup.sh (it installs torch, torchvision, lpips)";
      return;
    }
    dir_ = make_temp_dir("gaps_lpips_fixtures");
    const std::string command = std::string(GAPS_PYTHON) + " " + GAPS_TEST_SCRIPTS_DIR +
                                "/scripts/lpips_reference.py --out " + dir_ + " --lin " + kLinWeights;
    auto [rc, output] = run_command(command);
    if (rc == kMissingPythonModule) {
      skip_ = "the reference needs Python modules that " + std::string(GAPS_PYTHON) + " lacks: " + output;
      return;
    }
    if (rc != 0) {
      error_ = "fixture script failed (exit " + std::to_string(rc) + "): " + command + "\n" + output;
      return;
    }
    manifest_ = nlohmann::json::parse(read_file(dir_ + "/manifest.json"));
  }
  static void TearDownTestSuite() {
    if (!dir_.empty()) remove_tree(dir_);
  }
  void SetUp() override {
    if (!skip_.empty()) GTEST_SKIP() << skip_;
    ASSERT_TRUE(error_.empty()) << error_;
  }

  static std::string path(const std::string& name) { return dir_ + "/" + name; }
  static std::string backbone(const std::string& format) {
    return path(manifest_["backbones"][format].get<std::string>());
  }
  static at::Tensor read_image(const nlohmann::json& pair, const char* which) {
    const int64_t h = pair["height"].get<int64_t>(), w = pair["width"].get<int64_t>();
    at::Tensor image = at::empty({h, w, 3}, at::kFloat);
    const std::string bytes = read_file(path(pair[which].get<std::string>()));
    EXPECT_EQ(bytes.size(), static_cast<size_t>(image.numel() * 4)) << pair[which];
    std::memcpy(image.data_ptr(), bytes.data(), std::min<size_t>(bytes.size(), image.numel() * 4));
    return image;
  }
  static Lpips load_lpips(const std::string& format) {
    auto lpips = Lpips::load(kLinWeights, backbone(format));
    EXPECT_TRUE(lpips.ok()) << lpips.status();
    return std::move(lpips).value();
  }

  inline static std::string dir_;
  inline static std::string error_;
  inline static std::string skip_;
  inline static nlohmann::json manifest_;
};

}  // namespace gaps::test

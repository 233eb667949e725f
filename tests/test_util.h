#pragma once
// Helpers shared by the test suites.
#include <sys/wait.h>

#include <cstdio>
#include <filesystem>
#include <fstream>
#include <string>
#include <system_error>
#include <utility>

#include <gtest/gtest.h>
#include <nlohmann/json.hpp>
#include "common/io_util.h"

namespace gaps::test {

// Never std::filesystem::remove_all in binaries linking LibTorch (see common/io_util.h).
using ::gaps::remove_tree;

// Exit status and combined stdout and stderr of a shell command (the tests' Python references).
inline std::pair<int, std::string> run_command(const std::string& command) {
  std::string output;
  FILE* pipe = popen((command + " 2>&1").c_str(), "r");
  if (pipe == nullptr) return {-1, "popen failed"};
  char buffer[4096];
  while (size_t n = fread(buffer, 1, sizeof buffer, pipe)) output.append(buffer, n);
  const int status = pclose(pipe);
  return {WIFEXITED(status) ? WEXITSTATUS(status) : -1, output};
}

inline bool contains(const std::string& text, const std::string& part) { return text.find(part) != std::string::npos; }

// A whole file as text ("" when it cannot be read: the comparison that follows says what was expected).
inline std::string read_text(const std::filesystem::path& path) {
  std::ifstream f(path);
  return std::string(std::istreambuf_iterator<char>(f), {});
}

// A JSON file; a missing or malformed one throws, which fails the test naming the parse error.
inline nlohmann::json read_json(const std::filesystem::path& path) {
  std::ifstream f(path);
  return nlohmann::json::parse(f);
}

// A fresh folder per test (named after the suite and test), removed afterwards.
class TempDirTest : public ::testing::Test {
 protected:
  void SetUp() override {
    const auto* info = ::testing::UnitTest::GetInstance()->current_test_info();
    dir_ = std::filesystem::path(::testing::TempDir()) /
           ("gaps_" + std::string(info->test_suite_name()) + "_" + std::string(info->name()));
    remove_tree(dir_);
    std::filesystem::create_directories(dir_);
  }
  void TearDown() override { remove_tree(dir_); }

  // Writes bytes to a file below the folder (creating parent folders) and returns its path.
  std::filesystem::path write(const std::filesystem::path& relative, const std::string& bytes) {
    const auto path = dir_ / relative;
    std::filesystem::create_directories(path.parent_path());
    std::ofstream(path, std::ios::binary) << bytes;
    return path;
  }

  std::filesystem::path dir_;
};

}  // namespace gaps::test

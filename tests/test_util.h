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

// A test CA (ca.pem), a server certificate for localhost, a client certificate it signed and a self-signed
// "rogue" one, each with its key, in `dir`. False when openssl fails (callers skip first without openssl).
inline bool make_test_certificates(const std::filesystem::path& dir) {
  const std::string d = dir.string() + "/";
  const auto run = [](const std::string& command) { return std::system((command + " > /dev/null 2>&1").c_str()) == 0; };
  const auto sign = [&](const std::string& name, const std::string& ext) {
    return run("openssl req -newkey rsa:2048 -nodes -subj /CN=" + name + " -keyout " + d + name + ".key -out " + d +
               name + ".csr") &&
           run("printf '" + ext + "' > " + d + name + ".ext") &&
           run("openssl x509 -req -in " + d + name + ".csr -CA " + d + "ca.pem -CAkey " + d +
               "ca.key -CAcreateserial -days 1 -out " + d + name + ".pem -extfile " + d + name + ".ext");
  };
  return run("openssl req -x509 -newkey rsa:2048 -nodes -days 1 -subj /CN=gaps-test-ca -keyout " + d + "ca.key -out " +
             d + "ca.pem") &&
         sign("localhost", "subjectAltName=DNS:localhost\\nextendedKeyUsage=serverAuth") &&
         sign("client", "extendedKeyUsage=clientAuth") &&
         run("openssl req -x509 -newkey rsa:2048 -nodes -days 1 -subj /CN=rogue -keyout " + d + "rogue.key -out " + d +
             "rogue.pem");
}

}  // namespace gaps::test

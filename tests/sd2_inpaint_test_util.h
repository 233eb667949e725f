#pragma once
// The SD2 inpainting fixture (tests/fixtures/sd2_inpaint_tiny, made by tests/scripts/make_inpaint_fixtures.py),
// shared by sd2_inpaint_test.cpp and its GPU test in gpu/.
#include <fstream>
#include <string>
#include <vector>

#include <gtest/gtest.h>
#include <nlohmann/json.hpp>
#include "tests/sdxl_test_util.h"

namespace gaps::test {

inline std::string sd2_fixture_dir() { return std::string(GAPS_TEST_SCRIPTS_DIR) + "/fixtures/sd2_inpaint_tiny"; }
inline std::string sd2_model_dir() { return sd2_fixture_dir() + "/model"; }

inline sdxl::TensorMap sd2_reference(const std::string& name) { return fixture_reference(sd2_fixture_dir(), name); }

// The prompts, seed and settings of the recorded runs.
inline const nlohmann::json& sd2_inpaint_setup() {
  static const nlohmann::json setup = [] {
    std::ifstream in(sd2_fixture_dir() + "/reference/inpaint.json");
    return nlohmann::json::parse(in);
  }();
  return setup;
}

inline std::vector<std::string> sd2_prompts() { return sd2_inpaint_setup()["prompts"].get<std::vector<std::string>>(); }

}  // namespace gaps::test

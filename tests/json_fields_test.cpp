// The option structs' JSON: every field survives a round trip, and a misspelt key is an error naming it.
#include <string>

#include <gtest/gtest.h>
#include <nlohmann/json.hpp>

#include "gs_trainer/gaps/config.h"
#include "gs_trainer/train/train_config.h"

namespace gaps {
namespace {

template <typename Config>
std::string unknown_key_error(const nlohmann::json& j) {
  try {
    j.get<Config>();
  } catch (const nlohmann::json::exception& e) {
    return e.what();
  }
  return "";
}

TEST(JsonFields, TrainConfigRoundTripsAndRefusesUnknownKeys) {
  TrainConfig c;
  c.iterations = 1234;
  c.gaussians_per_variation = 2.5;
  c.device = "cpu";
  const nlohmann::json j = c;
  EXPECT_EQ(j.at("iterations"), 1234);
  const auto back = j.get<TrainConfig>();
  EXPECT_EQ(nlohmann::json(back), j);
  const std::string error = unknown_key_error<TrainConfig>({{"iterations", 10}, {"iteration", 10}});
  EXPECT_NE(error.find("unknown training option 'iteration'"), std::string::npos) << error;
}

TEST(JsonFields, GapsConfigRoundTripsAndRefusesUnknownKeys) {
  GapsConfig c;
  c.phase_interval = 250;
  c.admit_min_structure = 0.2;
  const nlohmann::json j = c;
  const auto back = j.get<GapsConfig>();
  EXPECT_EQ(back.phase_interval, 250);
  EXPECT_EQ(nlohmann::json(back), j);
  const std::string error = unknown_key_error<GapsConfig>({{"phase_intervall", 250}});
  EXPECT_NE(error.find("unknown GAPS option 'phase_intervall'"), std::string::npos) << error;
}

}  // namespace
}  // namespace gaps

// The options a user or a client hands over as JSON: a --config / --gaps-config file (the option tables'
// from_json) and a submitted job's options (set_fields into the proto, then the trainer's decoder
// run_options_from_proto). What decodes must be within the bounds that drive allocations and survive a round
// trip through JSON.
#include <nlohmann/json.hpp>

#include "common/limits.h"
#include "fuzz/fuzz_support.h"
#include "rpc/config_codec.h"
#include "server/job_config.h"

namespace {

void check_training(const gaps::TrainConfig& c) {
  if (c.max_gaussians < 0 || c.max_gaussians > gaps::kMaxGaussians || c.iterations < 1) __builtin_trap();
  const nlohmann::json once = c;
  const nlohmann::json twice = once.get<gaps::TrainConfig>();
  if (once != twice) __builtin_trap();
}

}  // namespace

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  const nlohmann::json j = nlohmann::json::parse(data, data + size, nullptr, /*allow_exceptions=*/false);
  if (j.is_discarded() || !j.is_object()) return 0;
  try {
    check_training(j.get<gaps::TrainConfig>());
  } catch (const std::exception&) {  // refused: unknown key, wrong type or out of range
  }
  try {
    const nlohmann::json once = j.get<gaps::GapsConfig>();
    if (once != nlohmann::json(once.get<gaps::GapsConfig>())) __builtin_trap();
  } catch (const std::exception&) {
  }
  gaps::v1::TrainConfig config;
  config.set_views(3);
  if (j.contains("random_points") && j["random_points"].is_number_integer())
    config.set_random_points(j["random_points"].get<int64_t>());
  nlohmann::json training = j, gaps_options = j;
  training.erase("random_points");
  gaps_options.erase("random_points");
  if (!gaps::rpc::set_fields(training, config.mutable_training()).ok() &&
      !gaps::rpc::set_fields(gaps_options, config.mutable_gaps()).ok())
    return 0;
  const auto o = gaps::run_options_from_proto(config, false, "", "cpu");
  if (!o.ok()) return 0;
  if (o->random_points < 1 || o->random_points > gaps::kMaxGaussians) __builtin_trap();
  check_training(o->config);
  return 0;
}

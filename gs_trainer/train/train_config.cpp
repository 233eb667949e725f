#include "gs_trainer/train/train_config.h"

#include <string>

#include <c10/core/Device.h>
#include <nlohmann/json.hpp>

namespace gaps {

absl::Status validate_train_config(const TrainConfig& c) {
  GAPS_TRAIN_CONFIG_OPTIONS(GAPS_CHECK_OPTION)
  try {
    const c10::Device device(c.device);
    if (!device.is_cpu() && !device.is_cuda()) throw std::runtime_error("not cpu or cuda");
  } catch (const std::exception&) {
    return absl::InvalidArgumentError(absl::StrCat("option 'device' = '", c.device, "' is not cpu, cuda or cuda:N"));
  }
  return absl::OkStatus();
}

std::vector<OptionInfo> train_config_options() {
  std::vector<OptionInfo> out;
  const std::string section = "training";
  GAPS_TRAIN_CONFIG_OPTIONS(GAPS_DESCRIBE_OPTION)
  return out;
}

void to_json(nlohmann::json& j, const TrainConfig& c) { GAPS_TRAIN_CONFIG_OPTIONS(GAPS_WRITE_OPTION) }

void from_json(const nlohmann::json& j, TrainConfig& c) {
  read_options(j, "training", [&](const std::string& key, const nlohmann::json& value) {
    GAPS_TRAIN_CONFIG_OPTIONS(GAPS_READ_OPTION)
    return false;
  });
  if (absl::Status s = validate_train_config(c); !s.ok())
    throw nlohmann::json::other_error::create(502, std::string(s.message()), &j);
}

}  // namespace gaps

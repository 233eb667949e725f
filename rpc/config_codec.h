#pragma once
// Hyperparameter messages (gaps.v1.TrainHyperparameters, GapsHyperparameters) <-> the JSON objects of
// TrainConfig / GapsConfig, whose keys are the proto field names. Only fields that are set travel, so
// unset ones keep the library defaults on the other side.
#include <google/protobuf/message.h>
#include <nlohmann/json.hpp>
#include "absl/status/status.h"

namespace gaps::rpc {

// The fields present in `message`, keyed by field name.
nlohmann::json present_fields(const google::protobuf::Message& message);
// Sets the message's fields from a JSON object; an unknown key or a value of the wrong type is
// INVALID_ARGUMENT naming it.
absl::Status set_fields(const nlohmann::json& object, google::protobuf::Message* message);

}  // namespace gaps::rpc

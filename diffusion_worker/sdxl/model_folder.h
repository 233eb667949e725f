#pragma once
// A diffusers-layout model folder: model_index.json naming the components, one subfolder per component
// with its config.json (scheduler_config.json for schedulers, tokenizer files for tokenizers) and
// weights in safetensors.
#include <string>

#include <nlohmann/json.hpp>
#include "absl/status/statusor.h"
#include "common/safetensors.h"

namespace gaps::sdxl {

class ModelFolder {
 public:
  // Reads root/model_index.json; an error when it is missing or not a JSON object.
  static absl::StatusOr<ModelFolder> open(const std::string& root);

  const std::string& root() const { return root_; }
  const nlohmann::json& index() const { return index_; }
  std::string component_dir(const std::string& component) const;

  // The component's class as model_index.json names it ("UNet2DConditionModel"); an error when the index
  // does not list the component.
  absl::StatusOr<std::string> component_class(const std::string& component) const;
  // component/config.json (or another file name in the component's folder) as JSON.
  absl::StatusOr<nlohmann::json> read_json(const std::string& component, const std::string& file = "config.json") const;
  // All tensors of the component's weights (read_folder_weights of its folder).
  absl::StatusOr<TensorMap> read_weights(const std::string& component, const std::string& variant = "") const;

 private:
  std::string root_;
  nlohmann::json index_;
};

// Every *.safetensors in dir (a sharded checkpoint is the union of its shards; a tensor in two files is an
// error); with variant "fp16" the *.fp16.safetensors files instead.
absl::StatusOr<TensorMap> read_folder_weights(const std::string& dir, const std::string& variant = "");

// Reads a JSON file; errors name the file.
absl::StatusOr<nlohmann::json> read_json_file(const std::string& path);

// config[key] as T with a default when absent or null; wrong types are an error naming the key.
template <typename T>
absl::StatusOr<T> config_value(const nlohmann::json& config, const std::string& key, const T& fallback) {
  if (!config.contains(key) || config[key].is_null()) return fallback;
  try {
    return config[key].get<T>();
  } catch (const std::exception& e) {
    return absl::InvalidArgumentError("config key '" + key + "' has the wrong type: " + config[key].dump());
  }
}

}  // namespace gaps::sdxl

#include "diffusion_worker/sdxl/model_folder.h"

#include <algorithm>
#include <filesystem>
#include <fstream>
#include <vector>

#include "absl/strings/match.h"
#include "absl/strings/str_cat.h"
#include "common/status_macros.h"

namespace gaps::sdxl {

absl::StatusOr<nlohmann::json> read_json_file(const std::string& path) {
  std::ifstream in(path);
  if (!in) return absl::NotFoundError(absl::StrCat("cannot read ", path));
  try {
    return nlohmann::json::parse(in);
  } catch (const std::exception& e) {
    return absl::InvalidArgumentError(absl::StrCat(path, " is not valid JSON: ", e.what()));
  }
}

absl::StatusOr<ModelFolder> ModelFolder::open(const std::string& root) {
  if (!std::filesystem::is_directory(root)) {
    return absl::NotFoundError(absl::StrCat("model folder ", root, " does not exist"));
  }
  ModelFolder folder;
  folder.root_ = root;
  GAPS_ASSIGN_OR_RETURN(folder.index_, read_json_file((std::filesystem::path(root) / "model_index.json").string()));
  if (!folder.index_.is_object())
    return absl::InvalidArgumentError(absl::StrCat(root, "/model_index.json is not a JSON object"));
  return folder;
}

std::string ModelFolder::component_dir(const std::string& component) const {
  return (std::filesystem::path(root_) / component).string();
}

absl::StatusOr<std::string> ModelFolder::component_class(const std::string& component) const {
  if (!index_.contains(component)) {
    return absl::NotFoundError(absl::StrCat(root_, "/model_index.json lists no component '", component, "'"));
  }
  const auto& entry = index_[component];
  if (!entry.is_array() || entry.size() != 2 || !entry[1].is_string()) {
    return absl::InvalidArgumentError(
        absl::StrCat(root_, "/model_index.json: component '", component, "' is not [library, class]: ", entry.dump()));
  }
  return entry[1].get<std::string>();
}

absl::StatusOr<nlohmann::json> ModelFolder::read_json(const std::string& component, const std::string& file) const {
  return read_json_file((std::filesystem::path(component_dir(component)) / file).string());
}

absl::StatusOr<TensorMap> ModelFolder::read_weights(const std::string& component, const std::string& variant) const {
  return read_folder_weights(component_dir(component), variant);
}

absl::StatusOr<TensorMap> read_folder_weights(const std::string& dir, const std::string& variant) {
  std::vector<std::string> files;
  std::error_code ec;
  for (const auto& entry : std::filesystem::directory_iterator(dir, ec)) {
    const std::string name = entry.path().filename().string();
    if (!absl::EndsWith(name, ".safetensors")) continue;
    const bool is_variant = !variant.empty() && absl::EndsWith(name, absl::StrCat(".", variant, ".safetensors"));
    const bool has_variant = absl::StrContains(name.substr(0, name.size() - 12), ".");
    if (variant.empty() ? !has_variant : is_variant) files.push_back(entry.path().string());
  }
  if (ec) return absl::NotFoundError(absl::StrCat("cannot list ", dir, ": ", ec.message()));
  if (files.empty()) {
    return absl::NotFoundError(
        absl::StrCat("no ", variant.empty() ? "" : variant + " ", "*.safetensors weights in ", dir));
  }
  std::sort(files.begin(), files.end());
  TensorMap all;
  for (const auto& file : files) {
    GAPS_ASSIGN_OR_RETURN(TensorMap part, read_safetensors(file));
    for (auto& [name, tensor] : part) {
      if (!all.emplace(name, tensor).second) {
        return absl::InvalidArgumentError(absl::StrCat("tensor '", name, "' appears in more than one file of ", dir));
      }
    }
  }
  return all;
}

}  // namespace gaps::sdxl

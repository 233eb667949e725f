#include "diffusion_worker/sdxl/weights.h"

#include <algorithm>
#include <utility>

#include <ATen/ATen.h>
#include "absl/strings/str_cat.h"
#include "absl/strings/str_join.h"

namespace gaps::sdxl {
namespace {

std::string shape_string(at::IntArrayRef shape) { return absl::StrCat("[", absl::StrJoin(shape, ", "), "]"); }

// At most a screenful of names; the count says how many more.
std::string name_list(const std::vector<std::string>& names) {
  constexpr size_t kShown = 12;
  std::vector<std::string> shown(names.begin(), names.begin() + std::min(names.size(), kShown));
  std::string text = absl::StrJoin(shown, ", ");
  if (names.size() > kShown) absl::StrAppend(&text, " and ", names.size() - kShown, " more");
  return text;
}

}  // namespace

std::string join_name(const std::string& prefix, const std::string& name) {
  return prefix.empty() ? name : absl::StrCat(prefix, ".", name);
}

WeightLoader::WeightLoader(std::string source, TensorMap tensors, at::TensorOptions options)
    : source_(std::move(source)),
      tensors_(std::move(tensors)),
      options_(options.memory_format(std::nullopt)),
      kernel_format_(options.memory_format_opt().value_or(at::MemoryFormat::Contiguous)) {}

at::Tensor WeightLoader::take(const std::string& name, at::IntArrayRef shape) {
  requested_.push_back({name, shape.vec()});
  const auto it = tensors_.find(name);
  if (it == tensors_.end()) {
    missing_.push_back(absl::StrCat(name, " ", shape_string(shape)));
    return at::empty(shape, options_);
  }
  taken_.insert(name);
  if (it->second.sizes() != shape) {
    misshaped_.push_back(absl::StrCat(name, " (checkpoint ", shape_string(it->second.sizes()), ", config expects ",
                                      shape_string(shape), ")"));
    return at::empty(shape, options_);
  }
  const at::Tensor t = it->second.to(options_);
  return t.dim() == 4 ? t.contiguous(kernel_format_) : t.contiguous();
}

absl::Status WeightLoader::finish() const {
  std::vector<std::string> unexpected;
  for (const auto& [name, tensor] : tensors_) {
    if (taken_.count(name) == 0) unexpected.push_back(name);
  }
  if (missing_.empty() && misshaped_.empty() && unexpected.empty()) return absl::OkStatus();
  std::vector<std::string> parts;
  if (!missing_.empty()) parts.push_back(absl::StrCat(missing_.size(), " missing: ", name_list(missing_)));
  if (!misshaped_.empty()) parts.push_back(absl::StrCat(misshaped_.size(), " mis-shaped: ", name_list(misshaped_)));
  if (!unexpected.empty()) parts.push_back(absl::StrCat(unexpected.size(), " unexpected: ", name_list(unexpected)));
  return absl::InvalidArgumentError(
      absl::StrCat("weights of ", source_, " do not match the config: ", absl::StrJoin(parts, "; ")));
}

}  // namespace gaps::sdxl

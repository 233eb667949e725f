#pragma once
// Hands a component's checkpoint tensors to the modules built from its config, by name and expected
// shape, and reports every missing, mis-shaped or unused tensor at the end (not just the first).
#include <set>
#include <string>
#include <vector>

#include <ATen/Tensor.h>
#include "absl/status/status.h"
#include "common/safetensors.h"

namespace gaps::sdxl {

// A tensor a module asks for: its name and shape.
struct TensorSpec {
  std::string name;
  std::vector<int64_t> shape;
};

class WeightLoader {
 public:
  // source names the checkpoint in errors; tensors are converted to options' dtype and device on take(), and
  // 4-d ones (convolution kernels) to options' memory format when it has one (channels-last convolutions).
  WeightLoader(std::string source, TensorMap tensors, at::TensorOptions options);

  // The tensor called name, which must have exactly shape. A missing or mis-shaped tensor is recorded
  // (finish() reports it) and an uninitialised tensor of the right shape is returned, so construction
  // can go on and collect all problems.
  at::Tensor take(const std::string& name, at::IntArrayRef shape);
  bool has(const std::string& name) const { return tensors_.count(name) > 0; }

  // OK when every tensor was taken exactly as expected; otherwise one error listing the missing,
  // mis-shaped and unexpected (never taken) tensors.
  absl::Status finish() const;

  const at::TensorOptions& options() const { return options_; }
  // The memory format 4-d tensors are given (Contiguous unless the options asked for another).
  at::MemoryFormat kernel_format() const { return kernel_format_; }
  // Every take() so far, in order: with an empty map on the meta device, a module's full weight list.
  const std::vector<TensorSpec>& requested() const { return requested_; }

 private:
  std::string source_;
  TensorMap tensors_;
  at::TensorOptions options_;  // without a memory format
  at::MemoryFormat kernel_format_;
  std::set<std::string> taken_;
  std::vector<std::string> missing_, misshaped_;
  std::vector<TensorSpec> requested_;
};

// "a.b" from prefix "a" and name "b" (name alone when prefix is empty).
std::string join_name(const std::string& prefix, const std::string& name);

}  // namespace gaps::sdxl

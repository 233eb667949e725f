#pragma once
// Divergence detection: a run whose loss or parameters stop being finite is stopped at once with an error
// naming the iteration and what became non-finite, instead of training on (and evaluating) garbage.
#include <vector>

#include <ATen/Tensor.h>
#include "absl/status/status.h"
#include "gs_trainer/model/gaussians.h"

namespace gaps {

class DivergenceGuard {
 public:
  // Checks every `check_every` iterations and at `last_iteration` (each check synchronises the device once).
  DivergenceGuard(int check_every, int last_iteration);

  // Called after every iteration with that iteration's loss (a device scalar). Returns an Aborted error
  // (see is_divergence) when the losses since the last check or the parameters are non-finite.
  absl::Status observe(int iteration, const at::Tensor& loss, const GaussianModel& model);

 private:
  int check_every_;
  int last_iteration_;
  int first_pending_ = 0;  // iteration of pending_losses_[0]
  std::vector<at::Tensor> pending_losses_;
};

// What is non-finite now: "" when loss and parameters are finite, else e.g.
// "loss (first at iteration 1234); parameters: log_scales 12 of 900 values, means 3 of 900 values".
std::string describe_non_finite(const GaussianModel& model, const std::vector<at::Tensor>& losses, int first_iteration);

// The status a DivergenceGuard stops a run with.
bool is_divergence(const absl::Status& status);

}  // namespace gaps

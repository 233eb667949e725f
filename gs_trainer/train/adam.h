#pragma once
// Adam over the Gaussian model's parameter tensors, one learning rate per tensor, whose state follows the
// model through densification (rows kept, rows appended with zero moments) and opacity resets.
#include <vector>

#include <ATen/Tensor.h>

#include "gs_trainer/model/gaussians.h"

namespace gaps {

class GaussianAdam {
 public:
  // Learning rates in the order of GaussianModel::parameters().
  GaussianAdam(GaussianModel& model, std::vector<double> learning_rates, double eps, double beta1 = 0.9,
               double beta2 = 0.999);

  void set_learning_rate(size_t index, double lr) { groups_[index].lr = lr; }
  double learning_rate(size_t index) const { return groups_[index].lr; }
  void step();
  void zero_grad();
  // Keeps the rows of every parameter (and its moments) where `keep` (N bool) is true.
  void keep_rows(const at::Tensor& keep);
  // Appends the rows of `extra` to every parameter, with zero moments.
  void append_rows(const GaussianModel& extra);
  // Zeroes the moments of one parameter (after its values were reset).
  void reset_state(size_t index);

 private:
  friend struct CheckpointAccess;  // gs_trainer/run/checkpoint.cpp saves and restores this state
  struct Group {
    at::Tensor* param;
    double lr;
    at::Tensor exp_avg, exp_avg_sq;
  };
  GaussianModel& model_;
  std::vector<Group> groups_;
  double eps_, beta1_, beta2_;
  int64_t steps_ = 0;
};

// 3DGS's exponential learning-rate decay from lr_init to lr_final over max_steps.
double exponential_lr(int64_t step, double lr_init, double lr_final, int64_t max_steps);

}  // namespace gaps

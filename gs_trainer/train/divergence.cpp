#include "gs_trainer/train/divergence.h"

#include <ATen/ATen.h>
#include "absl/strings/match.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_join.h"
#include "common/error_kind.h"

namespace gaps {
namespace {

constexpr char kDivergencePrefix[] = "training diverged at iteration ";
constexpr const char* kParameterNames[] = {"means", "log_scales", "quats", "opacity_logits", "sh_dc", "sh_rest"};

}  // namespace

DivergenceGuard::DivergenceGuard(int check_every, int last_iteration)
    : check_every_(std::max(1, check_every)), last_iteration_(last_iteration) {}

absl::Status DivergenceGuard::observe(int iteration, const at::Tensor& loss, const GaussianModel& model) {
  if (pending_losses_.empty()) first_pending_ = iteration;
  pending_losses_.push_back(loss.detach());
  if (iteration % check_every_ != 0 && iteration != last_iteration_) return absl::OkStatus();
  const std::string what = describe_non_finite(model, pending_losses_, first_pending_);
  pending_losses_.clear();
  if (what.empty()) return absl::OkStatus();
  return with_error_kind(absl::AbortedError(absl::StrCat(kDivergencePrefix, iteration, " (", model.size(),
                                                         " Gaussians): non-finite ", what)),
                         ErrorKind::kDiverged);
}

std::string describe_non_finite(const GaussianModel& model, const std::vector<at::Tensor>& losses,
                                int first_iteration) {
  // One transfer for everything: per loss a flag, per parameter tensor a count of non-finite values.
  std::vector<at::Tensor> counts;
  for (const auto& l : losses) counts.push_back(at::isfinite(l.reshape({})).logical_not().to(at::kLong));
  const std::vector<const at::Tensor*> params = {&model.means,          &model.log_scales, &model.quats,
                                                 &model.opacity_logits, &model.sh_dc,      &model.sh_rest};
  for (const at::Tensor* p : params)
    counts.push_back(p->defined() && p->numel() > 0 ? at::isfinite(p->detach()).logical_not().sum().to(at::kLong)
                                                    : at::zeros({}, at::kLong).to(model.means.device()));
  const at::Tensor host = at::stack(counts).cpu();
  const int64_t* c = host.data_ptr<int64_t>();
  std::vector<std::string> parts;
  for (size_t i = 0; i < losses.size(); ++i) {
    if (c[i] == 0) continue;
    parts.push_back(absl::StrCat("loss (first at iteration ", first_iteration + static_cast<int>(i), ")"));
    break;
  }
  std::vector<std::string> bad_params;
  for (size_t k = 0; k < params.size(); ++k) {
    const int64_t bad = c[losses.size() + k];
    if (bad > 0)
      bad_params.push_back(absl::StrCat(kParameterNames[k], " ", bad, " of ", params[k]->numel(), " values"));
  }
  if (!bad_params.empty()) parts.push_back(absl::StrCat("parameters: ", absl::StrJoin(bad_params, ", ")));
  return absl::StrJoin(parts, "; ");
}

bool is_divergence(const absl::Status& status) {
  return status.code() == absl::StatusCode::kAborted && absl::StartsWith(status.message(), kDivergencePrefix);
}

}  // namespace gaps

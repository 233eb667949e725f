#include "common/point_cloud.h"

#include <ATen/ATen.h>
#include "absl/strings/str_cat.h"

namespace gaps {

absl::Status check_point_cloud(const PointCloud& points, const std::string& where) {
  if (!points.xyz.defined() || points.xyz.dim() != 2 || points.xyz.size(1) != 3)
    return absl::InvalidArgumentError(absl::StrCat(where, ": points must be N x 3"));
  if (points.xyz.numel() == 0) return absl::OkStatus();
  const at::Tensor xyz = points.xyz.to(at::kDouble);
  if (!at::isfinite(xyz).all().item<bool>())
    return absl::InvalidArgumentError(absl::StrCat(where, ": non-finite point coordinates"));
  const at::Tensor beyond = (xyz.abs() > kMaxCoordinate).any(1);
  if (beyond.any().item<bool>()) {
    const int64_t first = beyond.nonzero()[0][0].item<int64_t>();
    return absl::InvalidArgumentError(absl::StrCat(
        where, ": point ", first, " has a coordinate beyond +-", kMaxCoordinate, " (", xyz[first][0].item<double>(),
        ", ", xyz[first][1].item<double>(), ", ", xyz[first][2].item<double>(), ")"));
  }
  return absl::OkStatus();
}

}  // namespace gaps

#include "gs_trainer/init/dense_mvs.h"

#include <chrono>
#include <optional>
#include <utility>

#include "absl/strings/str_cat.h"
#include "common/status_macros.h"

namespace gaps {
namespace {

// Depth ranges and sources of every view; a view without a range gets (0, 0) and no sources (PatchMatch
// leaves its depths 0; it can still be another view's source).
absl::StatusOr<PatchMatchInput> patchmatch_input(const std::vector<Camera>& cameras,
                                                 const std::vector<at::Tensor>& images, const SparseResult& sparse,
                                                 const PatchMatchOptions& patchmatch, const DenseOptions& range) {
  PatchMatchInput in{cameras, images, {}, {}};
  bool any = false;
  for (size_t r = 0; r < cameras.size(); ++r) {
    const auto bounds = view_depth_range(cameras[r], sparse.points.xyz, range);
    in.depth_ranges.push_back(bounds.value_or(std::make_pair(0.0, 0.0)));
    in.sources.push_back(
        bounds ? select_neighbors(static_cast<int>(r), cameras, sparse.point_views, patchmatch.max_source_views)
               : std::vector<int>{});
    any = any || !in.sources.back().empty();
  }
  if (!any)
    return absl::FailedPreconditionError("no view has a depth range (no sparse points, no near/far) and a neighbour");
  return in;
}

}  // namespace

absl::StatusOr<MvsResult> patchmatch_reconstruct(const std::vector<Camera>& cameras,
                                                 const std::vector<at::Tensor>& images, const SparseResult& sparse,
                                                 const PatchMatchOptions& patchmatch, const FusionOptions& fusion,
                                                 const DenseOptions& range, const StageControl& control) {
  if (cameras.size() < 2) return absl::FailedPreconditionError("multi-view stereo needs at least two views");
  GAPS_RETURN_IF_ERROR(check_view_images(cameras, images));
  GAPS_ASSIGN_OR_RETURN(const PatchMatchInput input, patchmatch_input(cameras, images, sparse, patchmatch, range));
  MvsResult result;
  for (const std::vector<int>& s : input.sources) result.stats.views_with_sources += s.empty() ? 0 : 1;
  const auto start = std::chrono::steady_clock::now();
  GAPS_ASSIGN_OR_RETURN(result.maps, patchmatch_stereo(input, patchmatch, control));
  result.stats.patchmatch_seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
  control.progress("fusion", 0, 1);
  GAPS_ASSIGN_OR_RETURN(result.fused, fuse_patchmatch_maps(result.maps, fusion));
  control.progress("fusion", 1, 1);
  result.stats.fusion = result.fused.stats;
  return result;
}

}  // namespace gaps

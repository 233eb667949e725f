#include "gs_trainer/gaps/candidate_renders.h"

#include <algorithm>

#include <ATen/ATen.h>

#include "gs_trainer/gaps/scores.h"
#include "gs_trainer/model/render.h"

namespace gaps {

int candidate_batch_size(int64_t gaussians, int width, int height, const at::Device& device, const GapsConfig& c) {
  if (!device.is_cuda()) return 1;
  constexpr int64_t kWorkingBytes = int64_t{1} << 30;
  constexpr int64_t kMaxBatch = 32;
  // Per Gaussian: 2D mean, conic, depth, radius, four features, opacity, tile count and its scan, and about four
  // (tile, Gaussian) pairs of 24 bytes (keys and ids, sorted and not). Per pixel: four feature channels, alpha,
  // transmittance, contributor count, the clamped colour, and the one-hot histogram codes of the entropy term
  // with their window means.
  const int64_t per_gaussian = 4 * (2 + 3 + 1 + 1 + 4 + 1) + 2 * 8 + 4 * 24;
  const int64_t per_pixel = 4 * (4 + 1 + 1 + 1 + 3) + 2 * 4 * std::max(2, c.entropy_bins);
  const int64_t per_view = per_gaussian * gaussians + per_pixel * int64_t{width} * height;
  return static_cast<int>(std::clamp<int64_t>(kWorkingBytes / std::max<int64_t>(per_view, 1), 1, kMaxBatch));
}

at::Tensor candidate_statistics(const GaussianModel& model, const std::vector<Camera>& cameras, const GapsConfig& c,
                                int batch) {
  if (cameras.empty()) return at::empty({0, 4}, at::kDouble);
  std::vector<at::Tensor> parts;
  render_same_size_batches(
      model, cameras,
      [&](const Camera& first) {
        return static_cast<size_t>(
            batch > 0 ? batch : candidate_batch_size(model.size(), first.width, first.height, model.means.device(), c));
      },
      [&](size_t, size_t, const RenderedViews& views) {
        parts.push_back(render_statistics(views.rgb, views.alpha, c));  // render_statistics clamps
      });
  // Kept on the device until every batch is queued: one copy to the host for the whole pool.
  return at::cat(parts).cpu().contiguous();
}

}  // namespace gaps

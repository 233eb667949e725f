#include "gs_trainer/run/options.h"

#include <algorithm>

#include "gs_trainer/init/initializer.h"
#include "gs_trainer/train/budget.h"

namespace gaps {

int longest_side(const std::vector<Camera>& cameras) {
  int side = 0;
  for (const Camera& c : cameras) side = std::max({side, c.width, c.height});
  return side;
}

bool auto_reads_larger_views(const RunOptions& o, const std::vector<Camera>& train) {
  if (o.init != "auto" || train.empty() || o.init_resolution != 0 ||
      o.sparse.max_image_side != SparseOptions{}.max_image_side ||
      o.patchmatch.max_image_side != PatchMatchOptions{}.max_image_side)
    return false;
  return 2 * longest_side(train) <= kAutoLargerViewsMaxSide && !views_surround_scene(train);
}

RunOptions with_auto_budget(const RunOptions& options, const std::vector<Camera>& train) {
  RunOptions used = options;
  double& density = used.config.gaussians_per_variation;
  if (density < 0)
    density = options.config.max_gaussians == 0 && auto_reads_larger_views(options, train)
                  ? kAutoLargerViewsGaussiansPerVariation
                  : kDefaultGaussiansPerVariation;
  return used;
}

}  // namespace gaps

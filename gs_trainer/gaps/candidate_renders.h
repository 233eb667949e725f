#pragma once
// Rendering a candidate pool for its scores: every candidate view rendered and measured (render_statistics in
// scores.h) in batches, so scoring hundreds of views waits on the device once per batch rather than twice per
// view.
#include <vector>

#include <ATen/Tensor.h>

#include "gs_trainer/gaps/config.h"
#include "gs_trainer/model/gaussians.h"
#include "gs_trainer/scene/camera.h"

namespace gaps {

// How many views of `gaussians` Gaussians at width × height one batch renders on `device`. On a GPU, as many as fit a
// fixed working memory (the projected Gaussians and features per view, the images and the entropy histograms),
// 1 to 32. On the CPU 1: nothing waits on a device there, and one view's temporaries stay in the caches (a batch
// of 16 fern views measured 25 % slower than one at a time).
int candidate_batch_size(int64_t gaussians, int width, int height, const at::Device& device, const GapsConfig& c);

// The render statistics (render_statistics' columns) of the full-fidelity render from each camera: K×4 doubles on
// the host, row k for cameras[k]. Consecutive cameras of one image size share a batch of `batch` views
// (0: candidate_batch_size's).
at::Tensor candidate_statistics(const GaussianModel& model, const std::vector<Camera>& cameras, const GapsConfig& c,
                                int batch = 0);

}  // namespace gaps

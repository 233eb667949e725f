#include "gs_trainer/init/patchmatch.h"

#include <algorithm>
#include <cmath>

#include <ATen/ATen.h>
#include <c10/core/DeviceGuard.h>
#include <Eigen/Dense>
#include "absl/strings/str_cat.h"
#include "common/status_macros.h"
#include "gs_trainer/init/patchmatch_backend.h"
#include "gs_trainer/init/patchmatch_host.h"
#include "gs_trainer/init/working_view.h"

namespace gaps {

absl::Status validate_patchmatch_options(const PatchMatchOptions& o) {
  if (o.max_image_side < 8)
    return absl::InvalidArgumentError(absl::StrCat("max_image_side ", o.max_image_side, " < 8"));
  if (o.window_radius < 1 || o.window_step < 1)
    return absl::InvalidArgumentError(
        absl::StrCat("window_radius and window_step must be >= 1, got ", o.window_radius, " and ", o.window_step));
  if (!(o.sigma_color > 0))
    return absl::InvalidArgumentError(absl::StrCat("sigma_color must be > 0, got ", o.sigma_color));
  if (o.iterations < 0 || o.geometric_iterations < 0)
    return absl::InvalidArgumentError("iterations and geometric_iterations must be >= 0");
  if (o.max_source_views < 1 || o.max_source_views > pm::kMaxSources)
    return absl::InvalidArgumentError(
        absl::StrCat("max_source_views must be in [1, ", pm::kMaxSources, "], got ", o.max_source_views));
  if (o.best_views < 1) return absl::InvalidArgumentError(absl::StrCat("best_views must be >= 1, got ", o.best_views));
  if (!(o.min_triangulation_angle_deg >= 0 && o.min_triangulation_angle_deg < 90))
    return absl::InvalidArgumentError("min_triangulation_angle_deg must be in [0, 90)");
  if (!(o.geometric_regularizer >= 0) || !(o.geometric_max_error_px > 0))
    return absl::InvalidArgumentError("geometric_regularizer must be >= 0 and geometric_max_error_px > 0");
  if (!(o.max_cost > 0)) return absl::InvalidArgumentError(absl::StrCat("max_cost must be > 0, got ", o.max_cost));
  return absl::OkStatus();
}

namespace {

absl::Status validate_view(const PatchMatchInput& in, size_t i) {
  const Camera& c = in.cameras[i];
  const at::Tensor& im = in.images[i];
  if (c.width <= 0 || c.height <= 0 || !(c.fx > 0) || !(c.fy > 0))
    return absl::InvalidArgumentError(absl::StrCat("camera ", i, " (", c.name, ") has no valid size or focal length"));
  if (!im.defined() || im.dim() != 3 || im.size(2) != 3 || !at::isFloatingType(im.scalar_type()))
    return absl::InvalidArgumentError(absl::StrCat("image ", i, " (", c.name, ") is not an HxWx3 float tensor"));
  if (im.size(0) != c.height || im.size(1) != c.width)
    return absl::InvalidArgumentError(absl::StrCat("image ", i, " (", c.name, ") is ", im.size(1), "x", im.size(0),
                                                   " but its camera is ", c.width, "x", c.height));
  if (im.device() != in.images[0].device())
    return absl::InvalidArgumentError(absl::StrCat("images on different devices: ", in.images[0].device().str(),
                                                   " and ", im.device().str(), " (image ", i, ")"));
  const auto [lo, hi] = in.depth_ranges[i];
  const bool none = lo == 0 && hi == 0;
  if (!none && !(std::isfinite(lo) && std::isfinite(hi) && lo > 0 && hi > lo))
    return absl::InvalidArgumentError(
        absl::StrCat("depth range of view ", i, " (", c.name, ") is empty or inverted: [", lo, ", ", hi, "]"));
  for (int s : in.sources[i]) {
    if (s < 0 || s >= static_cast<int>(in.cameras.size()) || s == static_cast<int>(i))
      return absl::InvalidArgumentError(
          absl::StrCat("source ", s, " of view ", i, " is out of range or the view itself"));
    if (std::count(in.sources[i].begin(), in.sources[i].end(), s) > 1)
      return absl::InvalidArgumentError(absl::StrCat("source ", s, " of view ", i, " is listed twice"));
  }
  return absl::OkStatus();
}

absl::Status validate(const PatchMatchInput& in) {
  const size_t n = in.cameras.size();
  if (in.images.size() != n || in.depth_ranges.size() != n || in.sources.size() != n)
    return absl::InvalidArgumentError(absl::StrCat("PatchMatch input sizes differ: ", n, " cameras, ", in.images.size(),
                                                   " images, ", in.depth_ranges.size(), " depth ranges, ",
                                                   in.sources.size(), " source lists"));
  for (size_t i = 0; i < n; ++i)
    if (absl::Status s = validate_view(in, i); !s.ok()) return s;
  return absl::OkStatus();
}

absl::StatusOr<const pm::Backend*> backend_for(const c10::Device& device) {
  if (!device.is_cuda()) return &pm::kCpuBackend;
#if defined(GAPS_CUDA_KERNELS)
  return &pm::kCudaBackend;
#else
  return absl::FailedPreconditionError(
      "gaps was built without CUDA kernels (GAPS_CUDA=OFF or no nvcc): PatchMatch got CUDA images; use --device cpu");
#endif
}

// One view at the working resolution. Downsampling and luma happen on the CPU whatever the device, so that
// both paths start from the same grey pixels (ATen's CPU and CUDA pooling sum in different orders).
struct WorkingView {
  Camera camera;
  at::Tensor image;  // HxWx3 float, CPU
  at::Tensor grey;   // HxW float, on the run's device
};

WorkingView make_working_view(const Camera& camera, const at::Tensor& image, int max_side, const c10::Device& device) {
  auto [cam, small] = working_view(camera, image.to(at::kCPU), max_side);
  WorkingView v{cam, small.clamp(0.0, 1.0), {}};
  const at::Tensor grey = v.image.select(2, 0) * 0.299 + v.image.select(2, 1) * 0.587 + v.image.select(2, 2) * 0.114;
  v.grey = grey.contiguous().to(device);
  return v;
}

pm::Source make_source(const Camera& ref, const WorkingView& src) {
  return pm::relative_source(ref, src.camera, src.grey.data_ptr<float>(), nullptr);
}

// A view's estimate on the run's device.
struct ViewState {
  at::Tensor depth, normal, cost;
};

ViewState empty_state(const Camera& c, const at::TensorOptions& opt) {
  return {at::zeros({c.height, c.width}, opt), at::zeros({c.height, c.width, 3}, opt),
          at::full({c.height, c.width}, pm::kMaxCost, opt)};
}

pm::Problem make_problem(size_t view, const std::vector<WorkingView>& views, const std::vector<int>& sources,
                         std::pair<double, double> range, const ViewState& state, const PatchMatchOptions& o) {
  pm::Problem p{};
  p.cam = pm::view_geometry(views[view].camera);
  p.grey = views[view].grey.data_ptr<float>();
  p.min_depth = static_cast<float>(range.first);
  p.max_depth = static_cast<float>(range.second);
  p.num_sources = static_cast<int>(sources.size());
  for (size_t k = 0; k < sources.size(); ++k) p.sources[k] = make_source(views[view].camera, views[sources[k]]);
  p.window = {o.window_radius, o.window_step, static_cast<float>(1.0 / o.sigma_color)};
  p.best_views = o.best_views;
  p.max_cos_triangulation = static_cast<float>(std::cos(o.min_triangulation_angle_deg * M_PI / 180.0));
  p.geometric = false;
  p.geometric_regularizer = static_cast<float>(o.geometric_regularizer);
  p.geometric_max_error = static_cast<float>(o.geometric_max_error_px);
  p.max_cost = static_cast<float>(o.max_cost);
  p.seed = o.seed;
  p.view = static_cast<uint32_t>(view);
  p.depth = state.depth.data_ptr<float>();
  p.normal = state.normal.data_ptr<float>();
  p.cost = state.cost.data_ptr<float>();
  return p;
}

void sweep(const pm::Backend& backend, const pm::Problem& p, int iteration) {
  backend.update(p, 0, iteration);
  backend.update(p, 1, iteration);
}

absl::Status stop_check(const StageControl& control, size_t view) {
  if (control.stop_requested()) return absl::CancelledError(absl::StrCat("PatchMatch stopped at view ", view));
  return absl::OkStatus();
}

}  // namespace

absl::StatusOr<std::vector<ViewDepthNormal>> patchmatch_stereo(const PatchMatchInput& input,
                                                               const PatchMatchOptions& options,
                                                               const StageControl& control) {
  if (absl::Status s = validate_patchmatch_options(options); !s.ok()) return s;
  if (absl::Status s = validate(input); !s.ok()) return s;
  const size_t n = input.cameras.size();
  if (n == 0) return std::vector<ViewDepthNormal>{};
  const c10::Device device = input.images[0].device();
  const absl::StatusOr<const pm::Backend*> backend = backend_for(device);
  if (!backend.ok()) return backend.status();
  const c10::DeviceGuard guard(device);
  const at::TensorOptions opt = at::TensorOptions(at::kFloat).device(device);

  std::vector<WorkingView> views;
  std::vector<ViewState> states;
  for (size_t i = 0; i < n; ++i) {
    views.push_back(make_working_view(input.cameras[i], input.images[i], options.max_image_side, device));
    states.push_back(empty_state(views.back().camera, opt));
  }
  // The views with something to estimate, each with its first max_source_views sources.
  std::vector<size_t> active;
  std::vector<pm::Problem> problems(n);
  for (size_t i = 0; i < n; ++i) {
    const auto& [lo, hi] = input.depth_ranges[i];
    if (input.sources[i].empty() || (lo == 0 && hi == 0)) continue;
    std::vector<int> sources = input.sources[i];
    if (static_cast<int>(sources.size()) > options.max_source_views) sources.resize(options.max_source_views);
    problems[i] = make_problem(i, views, sources, input.depth_ranges[i], states[i], options);
    active.push_back(i);
  }

  // Photometric sweeps of every view, then (COLMAP's order) geometric ones against those photometric maps.
  const int sweeps_per_view = options.iterations + (options.geometric_consistency ? options.geometric_iterations : 0);
  const int sweeps = static_cast<int>(active.size()) * sweeps_per_view;
  int swept = 0;
  control.progress("patchmatch", 0, sweeps);
  for (size_t i : active) {
    (*backend)->init(problems[i]);
    for (int it = 0; it < options.iterations; ++it) {
      GAPS_RETURN_IF_ERROR(stop_check(control, i));
      sweep(**backend, problems[i], it);
      control.progress("patchmatch", ++swept, sweeps);
    }
  }
  if (options.geometric_consistency) {
    std::vector<at::Tensor> photometric;
    for (const ViewState& s : states) photometric.push_back(s.depth.clone());
    for (size_t i : active) {
      pm::Problem& p = problems[i];
      p.geometric = true;
      for (int k = 0; k < p.num_sources; ++k) p.sources[k].depth = photometric[input.sources[i][k]].data_ptr<float>();
      (*backend)->rescore(p);
      for (int g = 0; g < options.geometric_iterations; ++g) {
        GAPS_RETURN_IF_ERROR(stop_check(control, i));
        sweep(**backend, p, options.iterations + g);
        control.progress("patchmatch", ++swept, sweeps);
      }
    }
  }
  for (size_t i : active) (*backend)->filter(problems[i]);

  std::vector<ViewDepthNormal> out;
  for (size_t i = 0; i < n; ++i)
    out.push_back({views[i].camera, views[i].image, states[i].depth.to(at::kCPU), states[i].normal.to(at::kCPU),
                   states[i].cost.to(at::kCPU)});
  return out;
}

}  // namespace gaps

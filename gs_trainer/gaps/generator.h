#pragma once
// The seam between the trainer and whatever produces pseudo-views. The trainer renders the current model
// at each selected pose and asks a Generator for images; in-process backends (diffusion_worker/) and the
// remote worker client implement this alike, so the trainer never knows where images come from.
#include <cmath>
#include <optional>
#include <string>
#include <vector>

#include <ATen/Tensor.h>
#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "gs_trainer/scene/camera.h"

namespace gaps {

// A ground-truth training view with the current model's render at its pose.
struct ReferenceView {
  Camera camera;
  at::Tensor image;         // H x W x 3 in [0, 1], CPU
  at::Tensor render_depth;  // H x W, the model's depth (eq. depth_render: alpha-weighted distance), CPU
  at::Tensor render_alpha;  // H x W, CPU
};

// Two-stage generation (sec. 3.3, eq. two_stage): a backend that inpaints regenerates the pixels whose
// render_depth is below depth_threshold (tau_d), dilated by a dilation x dilation square, in views with
// more than uncovered_fraction of them. The trainer sends GapsConfig's values with every request.
struct InpaintSettings {
  double depth_threshold = 0.01;     // tau_d, in render_depth's units (not given by the paper)
  double uncovered_fraction = 0.02;  // the paper's 2%
  int dilation = 15;                 // the paper's 15 x 15 kernel (odd)
};

// OK, or an InvalidArgument naming the first field out of range (the GapsConfig / proto field names).
inline absl::Status check_inpaint_settings(const InpaintSettings& s) {
  if (!(s.depth_threshold >= 0) || !std::isfinite(s.depth_threshold))
    return absl::InvalidArgumentError("inpaint_depth_threshold must be a finite number >= 0");
  if (!(s.uncovered_fraction >= 0 && s.uncovered_fraction < 1))
    return absl::InvalidArgumentError("inpaint_uncovered_fraction not in [0, 1)");
  if (s.dilation < 1 || s.dilation % 2 == 0) return absl::InvalidArgumentError("inpaint_dilation must be odd and >= 1");
  return absl::OkStatus();
}

struct GenerationRequest {
  Camera camera;                          // the pseudo pose
  at::Tensor render_rgb;                  // H x W x 3 full-fidelity render at the pose (no DropGaussian), CPU
  at::Tensor render_depth;                // H x W, eq. depth_render (divide by alpha for the expected distance)
  at::Tensor render_alpha;                // H x W
  double coverage = 0.0;                  // fraction of covered pixels
  double strength = 0.0;                  // img2img strength sigma(v), eq. adaptive_strength
  double control_scale = 0.0;             // s_cn(v), eq. adaptive_cn
  std::vector<ReferenceView> references;  // nearest GT views by pose distance, nearest first
  std::string prompt;
  uint64_t seed = 0;
  // nullopt: the backend's own inpainting options apply.
  std::optional<InpaintSettings> inpaint;
};

class Generator {
 public:
  virtual ~Generator() = default;
  // Backend name and version, e.g. "reproject 1".
  virtual std::string name() const = 0;
  // The model weights in use, one "component=path" per line; empty for a weight-free backend.
  virtual std::string weights_identity() const { return ""; }
  // Per-scene preparation before the first phase (e.g. LoRA training); may be a no-op for a backend
  // that learns nothing, which then says so in its documentation.
  virtual absl::Status adapt(const std::vector<ReferenceView>& views) = 0;
  // One H x W x 3 image in [0, 1] per request (CPU), in request order.
  virtual absl::StatusOr<std::vector<at::Tensor>> generate(const std::vector<GenerationRequest>& requests) = 0;
};

}  // namespace gaps

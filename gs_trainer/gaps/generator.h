#pragma once
// The seam between the trainer and whatever produces pseudo-views. The trainer renders the current model
// at each selected pose and asks a Generator for images; in-process backends (diffusion_worker/) and the
// remote worker client implement this alike, so the trainer never knows where images come from.
#include <algorithm>
#include <cmath>
#include <map>
#include <optional>
#include <string>
#include <vector>

#include <ATen/Tensor.h>
#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "absl/strings/str_cat.h"
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

// Scene adaptation (sec. 3.3, eq. lora): LoRA adapters of rank lora_rank trained for lora_steps steps on
// the ground-truth views, once, before the first phase (0 steps: none). The trainer sends GapsConfig's.
struct SceneAdaptation {
  int lora_rank = 4;
  int lora_steps = 50;
};

// OK, or an InvalidArgument naming the field out of range (the GapsConfig / proto field names).
inline absl::Status check_scene_adaptation(const SceneAdaptation& a) {
  if (a.lora_rank < 1) return absl::InvalidArgumentError(absl::StrCat("lora_rank must be >= 1, got ", a.lora_rank));
  if (a.lora_steps < 0) return absl::InvalidArgumentError(absl::StrCat("lora_steps must be >= 0, got ", a.lora_steps));
  return absl::OkStatus();
}

// lambda_ip (eq. ipadapter): the weight of the nearest reference view as image prompt; 0 = no image prompt.
inline absl::Status check_ip_adapter_scale(double scale) {
  if (!(scale >= 0) || !std::isfinite(scale))
    return absl::InvalidArgumentError(absl::StrCat("ip_adapter_scale must be a finite number >= 0, got ", scale));
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
  // lambda_ip; nullopt: the backend's own option applies.
  std::optional<double> ip_adapter_scale;
};

class Generator {
 public:
  virtual ~Generator() = default;
  // Backend name and version, e.g. "reproject 1".
  virtual std::string name() const = 0;
  // The model weights in use, one "component=path" per line; empty for a weight-free backend.
  virtual std::string weights_identity() const { return ""; }
  // Per-scene preparation before the first phase (e.g. LoRA training) as `adaptation` asks (nullopt: the
  // backend's own options); may be a no-op for a backend that learns nothing, which then says so in notes().
  virtual absl::Status adapt(const std::vector<ReferenceView>& views,
                             const std::optional<SceneAdaptation>& adaptation) = 0;
  // What the last adapt() learnt, for another instance of this backend with the same weights_identity() to
  // install instead of adapting anew (sdxl: its trained LoRA adapters, a safetensors file's bytes); empty when
  // it learnt nothing worth handing over (a weight-free backend, adapters loaded from a file at start-up).
  virtual absl::StatusOr<std::string> export_adaptation() const { return std::string(); }
  // Adopts another instance's export_adaptation() for these views and adaptation in place of adapt().
  virtual absl::Status install_adaptation(const std::vector<ReferenceView>& /*views*/,
                                          const std::optional<SceneAdaptation>& /*adaptation*/,
                                          std::string /*exported*/) {
    return absl::UnimplementedError(name() + " exports no adaptation, so it installs none");
  }
  // One H x W x 3 image in [0, 1] per request (CPU), in request order.
  virtual absl::StatusOr<std::vector<at::Tensor>> generate(const std::vector<GenerationRequest>& requests) = 0;
  // What the last adapt() or generate() call could not do of what it was asked (a control the backend has
  // no model for, an option that overrides the request), one sentence each; empty when it did everything.
  // A backend says so rather than ignoring a control silently; the trainer logs the notes with the phase.
  virtual std::vector<std::string> notes() const { return {}; }
  // Wall-clock seconds by stage of the last generate() call (for a remote backend, the scene adaptation it
  // ran first too), for the phases' time breakdown; empty for a backend without stages.
  virtual std::map<std::string, double> stage_seconds() const { return {}; }
  // Counts of the last generate() call other than time (a remote backend's bytes sent and received), for the
  // phases' record; empty for a backend without any.
  virtual std::map<std::string, double> counters() const { return {}; }
};

// The note of a backend without an IP-Adapter (`reason`, e.g. "reproject has no IP-Adapter") for the
// requests that ask for an image prompt (ip_adapter_scale > 0); nullopt when none does.
inline std::optional<std::string> unapplied_ip_adapter_note(const std::string& reason,
                                                            const std::vector<GenerationRequest>& requests) {
  int asking = 0;
  double largest = 0;
  for (const auto& r : requests) {
    if (r.ip_adapter_scale.value_or(0) <= 0) continue;
    ++asking;
    largest = std::max(largest, *r.ip_adapter_scale);
  }
  if (asking == 0) return std::nullopt;
  return absl::StrCat(reason, ": ", asking, "/", requests.size(), " requests asked for ip_adapter_scale ", largest,
                      ", generated without an image prompt");
}

}  // namespace gaps

#pragma once
// The "reproject" pseudo-view backend: a weight-free stand-in for the paper's four-fold constrained
// diffusion generator (sec. "Four-fold Constrained Pseudo-view Generation"). It re-projects real pixels of
// the nearest ground-truth views into the pseudo pose and keeps the paper's two control ideas:
//   * img2img anchoring (eq:adaptive_strength): where the current Gaussian render is reliable the output
//     stays close to it, and the warped content enters with weight sigma(v) = request.strength;
//   * two-stage generation (eq:two_stage): pixels nobody covers are dilated by a 15x15 kernel, inpainted
//     (OpenCV TELEA instead of SD2 inpainting) and composited over the stage-1 image.
// It produces plausible re-projections of observed pixels, not new content: regions that no reference saw
// and the model does not cover only ever receive inpainted (smeared) colour.
//
// Per request, exactly (H x W pseudo image, p a pixel, K = min(num_references, references.size())):
//  1. Forward warp, per reference k: each reference pixel with alpha >= min_reference_alpha is lifted to
//     3D at the expected distance depth/alpha along its ray, projected into the pseudo camera, and splatted
//     to a splat_footprint x splat_footprint block of pixels with tent weights (bilinear for 2x2, which
//     also closes the 1-pixel cracks of a magnifying warp) times the reference alpha. A soft z-buffer keeps
//     the nearest surface: a splat contributes to p only if its camera-z is within depth_tolerance
//     (relative) of the smallest z splatted to p. This gives colour C_k(p), weight sum W_k(p), depth z_k(p).
//  2. Blend references: only references whose z_k(p) is within depth_tolerance of min_k z_k(p) take part
//     (the nearest surface wins across references too). Their confidence is
//         c_k(p) = min(1, W_k(p)) / (theta_k(p) + angle_floor)^2,
//     theta_k(p) being the angle at the 3D point between the rays to the pseudo and the reference camera
//     centres (a reference seeing the point from the pseudo view's direction is trusted most; a reference
//     at the pseudo pose itself dominates). warped(p) = sum_k c_k C_k / sum_k c_k; covered where any
//     reference landed.
//  3. Anchor on the render (stage 1). R = render_alpha >= render_alpha_threshold (the coverage threshold):
//         I_s1 = (1 - sigma) render + sigma warped   where R and warped
//         I_s1 = render                             where R only
//         I_s1 = warped                             where warped only (the render has no coverage)
//  4. Two-stage fill: U = neither R nor warped; M = dilate(U, inpaint_dilation^2 square); I_s2 = TELEA
//     inpainting of I_s1 (8-bit) inside M with inpaint_radius; I = M I_s2 + (1 - M) I_s1 (eq:two_stage),
//     clamped to [0, 1]. If M would leave no known pixel, M = U; if nothing is known at all the image is the
//     nearest reference's mean colour.
// No randomness is involved: the output is a pure function of the request (request.seed is not used),
// so it is deterministic for a given seed. request.prompt and control_scale mean nothing here;
// request.render_depth is checked (shape, finite, >= 0) but not used: coverage comes from render_alpha.
#include <ATen/Tensor.h>

#include <string>
#include <vector>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "diffusion_worker/option_table.h"
#include "gs_trainer/gaps/generator.h"

namespace gaps {

struct ReprojectOptions {
  // Reference pixels below this alpha have no reliable depth and are not warped (> 0).
  double min_reference_alpha = 0.5;
  // How many of request.references (nearest first) are warped.
  int num_references = 2;
  // Side of the square block of pseudo pixels one reference pixel is splatted to (1 = nearest pixel,
  // 2 = bilinear, closes 1-pixel cracks).
  int splat_footprint = 2;
  // Relative camera-z band treated as the same surface by the soft z-buffer (0.02 = 2%).
  double depth_tolerance = 0.02;
  // Added to the angle theta_k in the blend weight 1 / (theta_k + floor)^2, in degrees (> 0).
  double angle_floor_deg = 0.5;
  // A render pixel with alpha >= this is covered (same meaning as GapsConfig::coverage_alpha_threshold).
  double render_alpha_threshold = 0.5;
  // cv::inpaint neighbourhood radius in pixels.
  double inpaint_radius = 3.0;
  // Side of the square kernel the uncovered mask is dilated with before inpainting (paper: 15; odd).
  int inpaint_dilation = 15;
};

// The options' JSON keys, what each accepts and sets.
const OptionTable<ReprojectOptions>& reproject_option_table();
// Errors name the offending option and its value.
absl::Status validate_reproject_options(const ReprojectOptions& options);
// A JSON object with any of the fields above, e.g. {"splat_footprint": 1}; empty or blank = defaults.
// Unknown keys, wrong types and invalid values are errors.
absl::StatusOr<ReprojectOptions> parse_reproject_options(const std::string& json_or_empty);

// One request's output with the intermediate images, for tests and diagnostics.
struct ReprojectResult {
  at::Tensor image;           // H x W x 3 float32 in [0, 1]: the pseudo-view
  at::Tensor warped;          // H x W x 3 float32: blended forward warp (step 2), 0 where not covered
  at::Tensor warp_covered;    // H x W bool: some reference landed here
  at::Tensor render_covered;  // H x W bool: render_alpha >= render_alpha_threshold
  at::Tensor inpaint_mask;    // H x W bool: M of eq:two_stage (the pixels taken from the inpainting)
};

// adapt() learns nothing for this backend: it only checks the views (shapes, finite depth/alpha) and
// returns OK, with a note when LoRA steps were asked for. generate() checks every request before doing any
// work; requests that ask for an IP-Adapter image prompt get a note (it has none).
class ReprojectGenerator : public Generator {
 public:
  explicit ReprojectGenerator(ReprojectOptions options = {});

  std::string name() const override;  // "reproject 1"
  absl::Status adapt(const std::vector<ReferenceView>& views,
                     const std::optional<SceneAdaptation>& adaptation) override;
  absl::StatusOr<std::vector<at::Tensor>> generate(const std::vector<GenerationRequest>& requests) override;
  std::vector<std::string> notes() const override { return notes_; }

  // One request, with intermediates.
  absl::StatusOr<ReprojectResult> generate_one(const GenerationRequest& request) const;
  const ReprojectOptions& options() const { return options_; }

 private:
  ReprojectOptions options_;
  std::vector<std::string> notes_;  // of the last adapt() or generate()
};

}  // namespace gaps

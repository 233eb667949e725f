#pragma once
// The "restore" pseudo-view backend: the render at the pseudo pose, restored by Real-ESRGAN x4plus
// (restore/restorer.h: shrunk by `downscale`, 4 by default, by area averaging, super-resolved 4x, resized back
// to its exact size). A render of a sparse-view model is blurred and streaked by floaters; the restored render
// keeps its content and geometry but gains photo-like sharp detail, a learned prior standing in for the
// diffusion model's. On crops of fern at -r 8 blurred by a Gaussian, the default 4x shrink helps heavily
// blurred renders (sigma 2.5 px: LPIPS to the photograph 0.551 -> 0.510, tests/restore_generator_test.cpp)
// but costs mildly blurred ones the detail they still have (sigma 1 px: 0.315 -> 0.473); downscale 1 restores
// those too (sigma 1 px: 0.315 -> 0.183, sigma 1.5 px: 0.470 -> 0.378) at 16x the compute.
//
// With compose = "reproject" the restored render is composed with the reproject backend's warp of the
// nearest ground-truth views (reproject_generator.h, run with its default options) where that warp is
// reliable, as reproject anchors its warp on the plain render (R = render_alpha >= 0.5, the render is
// covered; W = a reference landed there; sigma = request.strength):
//     I = (1 - sigma) restored + sigma warped   where R and W
//     I = restored                              where R only
//     I = reproject's image                     elsewhere (its warp where W only, its two-stage
//                                               inpainting where neither covers)
// so observed real pixels win where they exist and the restoration fills the rest of the covered view.
//
// The output is a deterministic function of the request (no randomness; the seed, prompt and ControlNet
// scale mean nothing here). In the plain mode the strength and references are not used.
#include <filesystem>
#include <memory>
#include <optional>
#include <string>
#include <vector>

#include <ATen/Tensor.h>
#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "diffusion_worker/option_table.h"
#include "diffusion_worker/reproject_generator.h"
#include "diffusion_worker/restore/restorer.h"
#include "diffusion_worker/restore/rrdbnet.h"
#include "gs_trainer/gaps/generator.h"

namespace gaps {

struct RestoreOptions {
  // The Real-ESRGAN x4plus safetensors file; "" = restore::default_realesrgan_weights_path() (what
  // scripts/setup.sh makes).
  std::string weights;
  std::string device = "cpu";  // cpu, cuda or cuda:N
  // auto = float16 on CUDA, float32 on the CPU; float16 needs CUDA.
  std::string dtype = "auto";
  // Low-resolution tile side (pixels of the 4x-shrunk render) the network runs on; 0 = the whole image.
  int tile = 0;
  // Pixels of context around each tile, cropped off its output.
  int tile_pad = 10;
  // Factor the render is shrunk by (area averaging) before the 4x network; 1 = not at all (the 4x output is
  // then shrunk 4x back).
  int downscale = 4;
  // none = the restored render; reproject = composed with reproject's warp (see above).
  std::string compose = "none";
};

// The options' JSON keys, what each accepts and sets.
const OptionTable<RestoreOptions>& restore_option_table();
// A JSON object with any of the fields above, e.g. {"device": "cuda", "compose": "reproject"}; empty or
// blank = defaults. Unknown keys, wrong types and invalid values are errors naming the key.
absl::StatusOr<RestoreOptions> parse_restore_options(const std::string& json_or_empty);

// One request's output with the intermediate images, for tests and diagnostics.
struct RestoreResult {
  at::Tensor image;     // H x W x 3 float32 in [0, 1]: the pseudo-view
  at::Tensor restored;  // H x W x 3 float32 in [0, 1]: the restored render
  // compose = reproject only (undefined otherwise): reproject's output and intermediates.
  std::optional<ReprojectResult> reprojected;
};

class RestoreGenerator : public Generator {
 public:
  // Loads the weights onto the device: a missing file is NotFound naming `bash scripts/setup.sh`; bad
  // option values (device, dtype) are InvalidArgument naming the option.
  static absl::StatusOr<std::unique_ptr<RestoreGenerator>> create(const RestoreOptions& options);

  std::string name() const override;              // "restore 1", or "restore 1 compose:reproject"
  std::string weights_identity() const override;  // "realesrgan=<weights file>"
  // Learns nothing: checks the views (compose = reproject: as reproject does) and notes LoRA steps asked for.
  absl::Status adapt(const std::vector<ReferenceView>& views,
                     const std::optional<SceneAdaptation>& adaptation) override;
  absl::StatusOr<std::vector<at::Tensor>> generate(const std::vector<GenerationRequest>& requests) override;
  std::vector<std::string> notes() const override { return notes_; }

  // One request, with intermediates.
  absl::StatusOr<RestoreResult> generate_one(const GenerationRequest& request) const;
  const RestoreOptions& options() const { return options_; }
  const std::filesystem::path& weights_path() const { return weights_path_; }

 private:
  RestoreGenerator(RestoreOptions options, std::filesystem::path weights_path, restore::RrdbNet net, at::Device device,
                   at::ScalarType dtype);
  // The request's checks (errors name it as request `index`); composing, also its re-projection.
  absl::StatusOr<std::optional<ReprojectResult>> check(const GenerationRequest& request, size_t index) const;
  // Restores the render and, given the re-projection, composes the two.
  absl::StatusOr<RestoreResult> finish(const GenerationRequest& request,
                                       std::optional<ReprojectResult> reprojected) const;

  RestoreOptions options_;
  std::filesystem::path weights_path_;
  restore::RrdbNet net_;
  at::Device device_;
  at::ScalarType dtype_;
  ReprojectGenerator reproject_;
  std::vector<std::string> notes_;  // of the last adapt() or generate()
};

}  // namespace gaps

#include "diffusion_worker/restore_generator.h"

#include <exception>
#include <utility>

#include <ATen/ATen.h>
#include <ATen/core/grad_mode.h>
#include <nlohmann/json.hpp>
#include "absl/strings/ascii.h"
#include "absl/strings/match.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_join.h"
#include "common/status_macros.h"
#include "diffusion_worker/restore/realesrgan_weights.h"

namespace gaps {
namespace {

absl::Status option_error(const std::string& key, const std::string& what) {
  return absl::InvalidArgumentError(absl::StrCat("restore option '", key, "': ", what));
}

// The render is all the plain mode reads, so it is all it checks; compose = reproject leaves the checks of
// the whole request to reproject.
absl::Status check_render(const GenerationRequest& q, const std::string& what) {
  const at::Tensor& r = q.render_rgb;
  if (!r.defined()) return absl::InvalidArgumentError(absl::StrCat(what, " render_rgb is missing"));
  if (q.camera.width <= 0 || q.camera.height <= 0)
    return absl::InvalidArgumentError(
        absl::StrCat(what, " camera is invalid (", q.camera.width, "x", q.camera.height, ")"));
  const std::vector<int64_t> expected = {q.camera.height, q.camera.width, 3};
  if (r.sizes() != at::IntArrayRef(expected))
    return absl::InvalidArgumentError(absl::StrCat(what, " render_rgb is ", absl::StrJoin(r.sizes(), "x"),
                                                   ", expected ", absl::StrJoin(expected, "x"), " (from its camera)"));
  if (!r.is_floating_point())
    return absl::InvalidArgumentError(absl::StrCat(what, " render_rgb must be floating point"));
  if (!at::isfinite(r).all().item<bool>())
    return absl::InvalidArgumentError(absl::StrCat(what, " render_rgb has NaN or infinite values"));
  return absl::OkStatus();
}

}  // namespace

const OptionTable<RestoreOptions>& restore_option_table() {
  using O = RestoreOptions;
  static const OptionTable<O> table(
      "restore",
      {
          string_option<O>("weights", &O::weights,
                           "Real-ESRGAN x4plus safetensors; \"\" = the one bash scripts/setup.sh makes"),
          string_option<O>("device", &O::device, "cpu, cuda or cuda:N"),
          string_option<O>("dtype", &O::dtype, "auto = float16 on CUDA, float32 on the CPU",
                           {"auto", "float32", "float16"}),
          integer_option<O>("tile", &O::tile, at_least(0), "low-resolution tile side the network runs on; 0 = whole"),
          integer_option<O>("tile_pad", &O::tile_pad, at_least(0), "context pixels around each tile"),
          integer_option<O>("downscale", &O::downscale, between(1, 4, "[]"),
                            "factor the render is shrunk by before the 4x network; 1 = not at all"),
          string_option<O>("compose", &O::compose, "reproject = compose with reproject's warp where it covers",
                           {"none", "reproject"}),
      });
  return table;
}

absl::StatusOr<RestoreOptions> parse_restore_options(const std::string& json_or_empty) {
  RestoreOptions options;
  if (absl::StripAsciiWhitespace(json_or_empty).empty()) return options;
  const nlohmann::json j = nlohmann::json::parse(json_or_empty, nullptr, /*allow_exceptions=*/false);
  if (j.is_discarded() || !j.is_object())
    return absl::InvalidArgumentError(absl::StrCat("restore options must be a JSON object, got: ", json_or_empty));
  GAPS_RETURN_IF_ERROR(restore_option_table().apply(j, options));
  return options;
}

RestoreGenerator::RestoreGenerator(RestoreOptions options, std::filesystem::path weights_path, restore::RrdbNet net,
                                   at::Device device, at::ScalarType dtype)
    : options_(std::move(options)),
      weights_path_(std::move(weights_path)),
      net_(std::move(net)),
      device_(device),
      dtype_(dtype) {}

absl::StatusOr<std::unique_ptr<RestoreGenerator>> RestoreGenerator::create(const RestoreOptions& options) {
  GAPS_RETURN_IF_ERROR(restore_option_table().validate(options));
  at::Device device(at::kCPU);
  try {
    device = at::Device(options.device);
  } catch (const std::exception&) {
    return option_error("device", absl::StrCat("'", options.device, "' is not a device (cpu, cuda, cuda:N)"));
  }
  if (!device.is_cuda() && !device.is_cpu()) return option_error("device", "only cpu and cuda are supported");
  if (device.is_cuda() && !at::hasCUDA())
    return option_error("device", "CUDA requested but no CUDA device is available");
  const at::ScalarType dtype =
      options.dtype == "float16" || (options.dtype == "auto" && device.is_cuda()) ? at::kHalf : at::kFloat;
  if (device.is_cpu() && dtype != at::kFloat) return option_error("dtype", "float16 needs CUDA (the CPU runs float32)");
  const std::filesystem::path path =
      options.weights.empty() ? restore::default_realesrgan_weights_path() : std::filesystem::path(options.weights);
  absl::StatusOr<restore::RrdbNet> net = absl::UnknownError("not loaded");
  try {
    net = restore::load_rrdbnet(path, restore::RrdbNetConfig{}, dtype, device);
  } catch (const std::exception& e) {
    // The copy onto the device is where an absent CUDA index or a full card shows up.
    return option_error("device", absl::StrCat("the weights could not be moved to ", device.str(), ": ", e.what()));
  }
  if (!net.ok()) return absl::Status(net.status().code(), absl::StrCat("restore backend: ", net.status().message()));
  return std::unique_ptr<RestoreGenerator>(new RestoreGenerator(options, path, *std::move(net), device, dtype));
}

std::string RestoreGenerator::name() const {
  return options_.compose == "reproject" ? "restore 1 compose:reproject" : "restore 1";
}

std::string RestoreGenerator::weights_identity() const { return absl::StrCat("realesrgan=", weights_path_.string()); }

absl::Status RestoreGenerator::adapt(const std::vector<ReferenceView>& views,
                                     const std::optional<SceneAdaptation>& adaptation) {
  notes_.clear();
  if (options_.compose == "reproject") {
    // reproject's own checks of the views; the adaptation is left out, so the note below is this backend's alone.
    GAPS_RETURN_IF_ERROR(reproject_.adapt(views, std::nullopt));
  } else if (views.empty()) {
    return absl::InvalidArgumentError("restore adapt: no ground-truth views");
  }
  if (adaptation && adaptation->lora_steps > 0) {
    notes_.push_back(absl::StrCat("restore has no model to adapt: the ", adaptation->lora_steps, " LoRA steps (rank ",
                                  adaptation->lora_rank, ") asked for were not run"));
  }
  return absl::OkStatus();
}

absl::StatusOr<std::optional<ReprojectResult>> RestoreGenerator::check(const GenerationRequest& request,
                                                                       size_t index) const {
  const std::string what = absl::StrCat("request ", index);
  if (options_.compose != "reproject") {
    GAPS_RETURN_IF_ERROR(check_render(request, what));
    return std::nullopt;
  }
  absl::StatusOr<ReprojectResult> reprojected = reproject_.generate_one(request);
  if (reprojected.ok()) return std::optional<ReprojectResult>(*std::move(reprojected));
  // reproject saw this one request alone, as its request 0.
  std::string message(reprojected.status().message());
  if (absl::StartsWith(message, "request 0")) message.replace(0, 9, what);
  return absl::Status(reprojected.status().code(), message);
}

absl::StatusOr<RestoreResult> RestoreGenerator::finish(const GenerationRequest& request,
                                                       std::optional<ReprojectResult> reprojected) const {
  RestoreResult result;
  result.reprojected = std::move(reprojected);
  try {
    // Not InferenceMode: the images leave as ordinary tensors, which the trainer may modify in place.
    const at::NoGradGuard no_grad;
    result.restored = restore::restore_image(net_, request.render_rgb, options_.downscale, device_, dtype_,
                                             {options_.tile, options_.tile_pad});
  } catch (const std::exception& e) {
    return absl::InternalError(absl::StrCat("restore failed on ", device_.str(), ": ", e.what()));
  }
  if (!result.reprojected) {
    result.image = result.restored;
    return result;
  }
  const ReprojectResult& r = *result.reprojected;
  const at::Tensor both = (r.render_covered & r.warp_covered).unsqueeze(-1);
  const at::Tensor render_only = (r.render_covered & ~r.warp_covered).unsqueeze(-1);
  const double sigma = request.strength;
  const at::Tensor blended = result.restored * (1 - sigma) + r.warped * sigma;
  result.image = at::where(both, blended, at::where(render_only, result.restored, r.image)).clamp(0, 1).contiguous();
  return result;
}

absl::StatusOr<RestoreResult> RestoreGenerator::generate_one(const GenerationRequest& request) const {
  GAPS_ASSIGN_OR_RETURN(std::optional<ReprojectResult> reprojected, check(request, 0));
  return finish(request, std::move(reprojected));
}

absl::StatusOr<std::vector<at::Tensor>> RestoreGenerator::generate(const std::vector<GenerationRequest>& requests) {
  notes_.clear();
  // Every request is checked (and, composing, re-projected: a few tens of milliseconds each) before the
  // network runs on any.
  std::vector<std::optional<ReprojectResult>> reprojected;
  for (size_t i = 0; i < requests.size(); ++i) {
    GAPS_ASSIGN_OR_RETURN(std::optional<ReprojectResult> r, check(requests[i], i));
    reprojected.push_back(std::move(r));
  }
  std::vector<at::Tensor> images;
  for (size_t i = 0; i < requests.size(); ++i) {
    absl::StatusOr<RestoreResult> result = finish(requests[i], std::move(reprojected[i]));
    if (!result.ok())
      return absl::Status(result.status().code(), absl::StrCat("request ", i, ": ", result.status().message()));
    images.push_back(std::move(result->image));
  }
  if (auto note = unapplied_ip_adapter_note("restore has no IP-Adapter", requests)) notes_.push_back(*note);
  return images;
}

}  // namespace gaps

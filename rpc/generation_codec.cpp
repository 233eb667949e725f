#include "rpc/generation_codec.h"

#include <cmath>
#include <map>
#include <optional>

#include "absl/strings/str_cat.h"
#include "common/status_macros.h"
#include "rpc/codec.h"

namespace gaps::rpc {

void encode_reference(const ReferenceView& view, v1::ReferenceView* out) {
  encode_camera(view.camera, out->mutable_camera());
  encode_raw(view.image, out->mutable_image());
  encode_raw(view.render_depth, out->mutable_render_depth());
  encode_raw(view.render_alpha, out->mutable_render_alpha());
}

absl::StatusOr<ReferenceView> decode_reference(const v1::ReferenceView& in, const std::string& what) {
  ReferenceView view;
  GAPS_ASSIGN_OR_RETURN(view.camera, decode_camera(in.camera(), absl::StrCat(what, " camera")));
  const int64_t h = view.camera.height, w = view.camera.width;
  GAPS_ASSIGN_OR_RETURN(view.image, decode_tensor_shaped(in.image(), {h, w, 3}, absl::StrCat(what, " image")));
  GAPS_ASSIGN_OR_RETURN(view.render_depth,
                        decode_tensor_shaped(in.render_depth(), {h, w}, absl::StrCat(what, " render_depth")));
  GAPS_ASSIGN_OR_RETURN(view.render_alpha,
                        decode_tensor_shaped(in.render_alpha(), {h, w}, absl::StrCat(what, " render_alpha")));
  return view;
}

namespace {

// All three fields or none.
absl::StatusOr<std::optional<InpaintSettings>> decode_inpaint_settings(const v1::PoseConstraints& p,
                                                                       const std::string& what) {
  const int given = p.has_inpaint_depth_threshold() + p.has_inpaint_uncovered_fraction() + p.has_inpaint_dilation();
  if (given == 0) return std::nullopt;
  if (given != 3) {
    return absl::InvalidArgumentError(absl::StrCat(
        what, ": give all of inpaint_depth_threshold, inpaint_uncovered_fraction and inpaint_dilation, or none"));
  }
  const InpaintSettings s{p.inpaint_depth_threshold(), p.inpaint_uncovered_fraction(), p.inpaint_dilation()};
  if (absl::Status range = check_inpaint_settings(s); !range.ok())
    return absl::InvalidArgumentError(absl::StrCat(what, ": ", range.message()));
  return s;
}

// Both fields or none.
absl::StatusOr<std::optional<SceneAdaptation>> decode_adaptation(const v1::AdaptSceneBatch& b) {
  if (!b.has_lora_rank() && !b.has_lora_steps()) return std::nullopt;
  if (!b.has_lora_rank() || !b.has_lora_steps())
    return absl::InvalidArgumentError("AdaptSceneBatch: give both lora_rank and lora_steps, or neither");
  const SceneAdaptation a{b.lora_rank(), b.lora_steps()};
  if (absl::Status range = check_scene_adaptation(a); !range.ok())
    return absl::InvalidArgumentError(absl::StrCat("AdaptSceneBatch: ", range.message()));
  return a;
}

}  // namespace

void encode_adapt_batch(const std::string& scene_id, const std::vector<ReferenceView>& views,
                        const std::optional<SceneAdaptation>& adaptation, v1::AdaptSceneBatch* out) {
  out->set_scene_id(scene_id);
  for (const auto& v : views) encode_reference(v, out->add_references());
  if (adaptation) {
    out->set_lora_rank(adaptation->lora_rank);
    out->set_lora_steps(adaptation->lora_steps);
  }
}

absl::StatusOr<AdaptRequest> decode_adapt_batch(const v1::AdaptSceneBatch& batch) {
  AdaptRequest out;
  for (int i = 0; i < batch.references_size(); ++i) {
    GAPS_ASSIGN_OR_RETURN(ReferenceView view, decode_reference(batch.references(i), absl::StrCat("reference ", i)));
    out.views.push_back(std::move(view));
  }
  GAPS_ASSIGN_OR_RETURN(out.adaptation, decode_adaptation(batch));
  return out;
}

void encode_generation_batch(const std::vector<GenerationRequest>& requests, v1::GenerateBatch* out) {
  std::map<std::string, int> index;  // camera name -> position in out->references
  for (const auto& q : requests) {
    v1::PoseConstraints* pose = out->add_poses();
    encode_camera(q.camera, pose->mutable_camera());
    encode_raw(q.render_rgb, pose->mutable_render_rgb());
    encode_raw(q.render_depth, pose->mutable_render_depth());
    encode_raw(q.render_alpha, pose->mutable_render_alpha());
    pose->set_coverage(q.coverage);
    pose->set_strength(q.strength);
    pose->set_control_scale(q.control_scale);
    pose->set_prompt(q.prompt);
    pose->set_seed(q.seed);
    if (q.ip_adapter_scale) pose->set_ip_adapter_scale(*q.ip_adapter_scale);
    if (q.inpaint) {
      pose->set_inpaint_depth_threshold(q.inpaint->depth_threshold);
      pose->set_inpaint_uncovered_fraction(q.inpaint->uncovered_fraction);
      pose->set_inpaint_dilation(q.inpaint->dilation);
    }
    for (const auto& r : q.references) {
      auto [it, inserted] = index.emplace(r.camera.name, out->references_size());
      if (inserted) encode_reference(r, out->add_references());
      pose->add_reference_order(it->second);
    }
  }
}

absl::StatusOr<std::vector<GenerationRequest>> decode_generation_batch(const v1::GenerateBatch& batch) {
  std::vector<ReferenceView> references;
  for (int i = 0; i < batch.references_size(); ++i) {
    GAPS_ASSIGN_OR_RETURN(ReferenceView r, decode_reference(batch.references(i), absl::StrCat("reference ", i)));
    references.push_back(std::move(r));
  }
  std::vector<GenerationRequest> requests;
  for (int k = 0; k < batch.poses_size(); ++k) {
    const v1::PoseConstraints& p = batch.poses(k);
    const std::string what = absl::StrCat("pose ", k);
    GenerationRequest q;
    GAPS_ASSIGN_OR_RETURN(q.camera, decode_camera(p.camera(), absl::StrCat(what, " camera")));
    const int64_t h = q.camera.height, w = q.camera.width;
    GAPS_ASSIGN_OR_RETURN(q.render_rgb,
                          decode_tensor_shaped(p.render_rgb(), {h, w, 3}, absl::StrCat(what, " render_rgb")));
    GAPS_ASSIGN_OR_RETURN(q.render_depth,
                          decode_tensor_shaped(p.render_depth(), {h, w}, absl::StrCat(what, " render_depth")));
    GAPS_ASSIGN_OR_RETURN(q.render_alpha,
                          decode_tensor_shaped(p.render_alpha(), {h, w}, absl::StrCat(what, " render_alpha")));
    for (double v : {p.coverage(), p.strength(), p.control_scale()})
      if (!std::isfinite(v)) return absl::InvalidArgumentError(absl::StrCat(what, ": non-finite control value"));
    // The Generator seam does not carry it yet; refusing beats silently ignoring what the caller asked for.
    if (p.has_inpaint_mask())
      return absl::UnimplementedError(absl::StrCat(what, ": inpaint_mask is not supported by this worker's backends"));
    if (p.has_ip_adapter_scale()) {
      if (absl::Status range = check_ip_adapter_scale(p.ip_adapter_scale()); !range.ok())
        return absl::InvalidArgumentError(absl::StrCat(what, ": ", range.message()));
      q.ip_adapter_scale = p.ip_adapter_scale();
    }
    q.coverage = p.coverage();
    q.strength = p.strength();
    q.control_scale = p.control_scale();
    q.prompt = p.prompt();
    q.seed = p.seed();
    GAPS_ASSIGN_OR_RETURN(q.inpaint, decode_inpaint_settings(p, what));
    for (int r : p.reference_order()) {
      if (r < 0 || r >= static_cast<int>(references.size()))
        return absl::InvalidArgumentError(
            absl::StrCat(what, ": reference index ", r, " out of range (", references.size(), " references)"));
      q.references.push_back(references[r]);
    }
    requests.push_back(std::move(q));
  }
  return requests;
}

}  // namespace gaps::rpc

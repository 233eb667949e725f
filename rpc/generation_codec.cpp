#include "rpc/generation_codec.h"

#include <cmath>
#include <map>
#include <optional>
#include <set>

#include "absl/strings/str_cat.h"
#include "common/status_macros.h"
#include "rpc/codec.h"

namespace gaps::rpc {

namespace {

// Encodes `tensor` now, or lays it out and leaves its conversion to `part`'s sender when there is a part.
absl::Status put_tensor(const at::Tensor& tensor, TensorEncoding encoding, SharedArena* arena, const std::string& what,
                        v1::Tensor* out, MessagePart* part) {
  if (part == nullptr) return encode_tensor(tensor, encoding, arena, what, out);
  GAPS_ASSIGN_OR_RETURN(DeferredPayload payload, lay_out_tensor(tensor, encoding, arena, what, out));
  part->payloads.push_back(std::move(payload));
  return absl::OkStatus();
}

absl::Status encode_reference_as(const ReferenceView& view, const TensorTransfer& transfer, const std::string& what,
                                 v1::ReferenceView* out, MessagePart* part = nullptr) {
  encode_camera(view.camera, out->mutable_camera());
  GAPS_RETURN_IF_ERROR(put_tensor(view.image, transfer.images, transfer.arena, absl::StrCat(what, " image"),
                                  out->mutable_image(), part));
  GAPS_RETURN_IF_ERROR(put_tensor(view.render_depth, transfer.depths, transfer.arena,
                                  absl::StrCat(what, " render_depth"), out->mutable_render_depth(), part));
  return put_tensor(view.render_alpha, transfer.images, transfer.arena, absl::StrCat(what, " render_alpha"),
                    out->mutable_render_alpha(), part);
}

absl::StatusOr<ReferenceView> decode_reference_in(const v1::ReferenceView& in, const std::string& what,
                                                  const SharedRegion* region) {
  ReferenceView view;
  GAPS_ASSIGN_OR_RETURN(view.camera, decode_camera(in.camera(), absl::StrCat(what, " camera")));
  const int64_t h = view.camera.height, w = view.camera.width;
  GAPS_ASSIGN_OR_RETURN(view.image, decode_tensor_shaped(in.image(), {h, w, 3}, absl::StrCat(what, " image"), region));
  GAPS_ASSIGN_OR_RETURN(view.render_depth,
                        decode_tensor_shaped(in.render_depth(), {h, w}, absl::StrCat(what, " render_depth"), region));
  GAPS_ASSIGN_OR_RETURN(view.render_alpha,
                        decode_tensor_shaped(in.render_alpha(), {h, w}, absl::StrCat(what, " render_alpha"), region));
  return view;
}

uint64_t view_bytes(const at::Tensor& rgb, const at::Tensor& depth, const at::Tensor& alpha, TensorEncoding images) {
  return arena_bytes(encoded_bytes(rgb, images)) + arena_bytes(encoded_bytes(depth, TensorEncoding::kFloat32)) +
         arena_bytes(encoded_bytes(alpha, images));
}

}  // namespace

TensorEncoding depth_encoding_for(TensorEncoding images, bool shared_memory) {
  return images == TensorEncoding::kUint8 && !shared_memory ? TensorEncoding::kFloat16 : TensorEncoding::kFloat32;
}

void encode_reference(const ReferenceView& view, v1::ReferenceView* out) {
  // Float32 into the message fails on nothing.
  encode_reference_as(view, {}, "reference", out).IgnoreError();
}

absl::StatusOr<ReferenceView> decode_reference(const v1::ReferenceView& in, const std::string& what) {
  return decode_reference_in(in, what, nullptr);
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
                        const std::optional<SceneAdaptation>& adaptation, v1::AdaptSceneBatch* out,
                        const std::string& exported) {
  out->set_scene_id(scene_id);
  out->set_adaptation_export(exported);
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
  out.exported = batch.adaptation_export();
  return out;
}

SharedLayout shared_layout(const std::vector<GenerationRequest>& requests, TensorEncoding images) {
  SharedLayout layout;
  std::set<std::string> references;
  for (const auto& q : requests) {
    layout.request_bytes += view_bytes(q.render_rgb, q.render_depth, q.render_alpha, images);
    layout.answer_bytes += arena_bytes(encoded_bytes(q.render_rgb, images));
    for (const auto& r : q.references)
      if (references.insert(r.camera.name).second)
        layout.request_bytes += view_bytes(r.image, r.render_depth, r.render_alpha, images);
  }
  return layout;
}

namespace {

// The next part of `parts` (nullptr when there are none), for element `index` of field `field`.
MessagePart* next_part(std::vector<MessagePart>* parts, int field, int index) {
  if (parts == nullptr) return nullptr;
  parts->push_back({field, index, {}});
  return &parts->back();
}

}  // namespace

absl::Status encode_generation_batch(const std::vector<GenerationRequest>& requests, v1::GenerateBatch* out,
                                     const TensorTransfer& transfer, std::vector<MessagePart>* parts) {
  out->set_answer_encoding(to_proto(transfer.images));
  std::map<std::string, int> index;  // camera name -> position in out->references
  for (size_t k = 0; k < requests.size(); ++k) {
    const GenerationRequest& q = requests[k];
    const std::string what = absl::StrCat("pose ", k);
    MessagePart* part = next_part(parts, v1::GenerateBatch::kPosesFieldNumber, static_cast<int>(k));
    v1::PoseConstraints* pose = out->add_poses();
    encode_camera(q.camera, pose->mutable_camera());
    GAPS_RETURN_IF_ERROR(put_tensor(q.render_rgb, transfer.images, transfer.arena, absl::StrCat(what, " render_rgb"),
                                    pose->mutable_render_rgb(), part));
    GAPS_RETURN_IF_ERROR(put_tensor(q.render_depth, transfer.depths, transfer.arena,
                                    absl::StrCat(what, " render_depth"), pose->mutable_render_depth(), part));
    GAPS_RETURN_IF_ERROR(put_tensor(q.render_alpha, transfer.images, transfer.arena,
                                    absl::StrCat(what, " render_alpha"), pose->mutable_render_alpha(), part));
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
      if (inserted)
        GAPS_RETURN_IF_ERROR(
            encode_reference_as(r, transfer, absl::StrCat("reference ", r.camera.name), out->add_references(),
                                next_part(parts, v1::GenerateBatch::kReferencesFieldNumber, it->second)));
      pose->add_reference_order(it->second);
    }
  }
  return absl::OkStatus();
}

absl::Status encode_answer(const std::vector<at::Tensor>& images, const TensorTransfer& transfer,
                           v1::GenerateResult* out, std::vector<MessagePart>* parts) {
  SharedArena* arena = transfer.arena;
  if (arena != nullptr) {
    uint64_t need = 0;
    for (const at::Tensor& image : images) need += arena_bytes(encoded_bytes(image, transfer.images));
    if (need > arena->region().size() - std::min(arena->used_end(), arena->region().size())) arena = nullptr;
  }
  for (size_t k = 0; k < images.size(); ++k)
    GAPS_RETURN_IF_ERROR(put_tensor(images[k], transfer.images, arena, absl::StrCat("image ", k), out->add_images(),
                                    next_part(parts, v1::GenerateResult::kImagesFieldNumber, static_cast<int>(k))));
  return absl::OkStatus();
}

absl::StatusOr<std::vector<GenerationRequest>> decode_generation_batch(const v1::GenerateBatch& batch,
                                                                       const SharedRegion* region) {
  std::vector<ReferenceView> references;
  for (int i = 0; i < batch.references_size(); ++i) {
    GAPS_ASSIGN_OR_RETURN(ReferenceView r,
                          decode_reference_in(batch.references(i), absl::StrCat("reference ", i), region));
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
                          decode_tensor_shaped(p.render_rgb(), {h, w, 3}, absl::StrCat(what, " render_rgb"), region));
    GAPS_ASSIGN_OR_RETURN(q.render_depth,
                          decode_tensor_shaped(p.render_depth(), {h, w}, absl::StrCat(what, " render_depth"), region));
    GAPS_ASSIGN_OR_RETURN(q.render_alpha,
                          decode_tensor_shaped(p.render_alpha(), {h, w}, absl::StrCat(what, " render_alpha"), region));
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

#pragma once
// GenerationRequest / ReferenceView / SceneAdaptation <-> gaps.v1 generation messages. Reference views
// shared by the poses of a batch travel once (matched by camera name), each pose keeping its own
// nearest-first order. Tensors travel as raw float32, so a remote backend sees exactly what an in-process
// one would. Decoding checks the controls' ranges: INVALID_ARGUMENT naming the field.
#include <optional>
#include <string>
#include <vector>

#include "absl/status/statusor.h"
#include "gaps/v1/diffusion_worker.pb.h"
#include "gs_trainer/gaps/generator.h"

namespace gaps::rpc {

void encode_reference(const ReferenceView& view, v1::ReferenceView* out);
absl::StatusOr<ReferenceView> decode_reference(const v1::ReferenceView& view, const std::string& what);

// What an AdaptScene call asks: adapt to these views, as `adaptation` says (nullopt: the backend's options).
struct AdaptRequest {
  std::vector<ReferenceView> views;
  std::optional<SceneAdaptation> adaptation;
};

void encode_adapt_batch(const std::string& scene_id, const std::vector<ReferenceView>& views,
                        const std::optional<SceneAdaptation>& adaptation, v1::AdaptSceneBatch* out);
absl::StatusOr<AdaptRequest> decode_adapt_batch(const v1::AdaptSceneBatch& batch);

void encode_generation_batch(const std::vector<GenerationRequest>& requests, v1::GenerateBatch* out);
absl::StatusOr<std::vector<GenerationRequest>> decode_generation_batch(const v1::GenerateBatch& batch);

}  // namespace gaps::rpc

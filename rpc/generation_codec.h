#pragma once
// GenerationRequest / ReferenceView / SceneAdaptation <-> gaps.v1 generation messages. Reference views
// shared by the poses of a batch travel once (matched by camera name), each pose keeping its own
// nearest-first order. Tensors travel as raw float32, so that a remote backend sees exactly what an
// in-process one would, or compact (`TensorTransfer`): colour and alpha as bytes, depth as float16 in the
// message or float32 in a shared-memory region. Decoding checks the controls' ranges: INVALID_ARGUMENT naming
// the field.
#include <optional>
#include <string>
#include <vector>

#include "absl/status/statusor.h"
#include "gaps/v1/diffusion_worker.pb.h"
#include "gs_trainer/gaps/generator.h"
#include "rpc/codec.h"
#include "rpc/shared_memory.h"
#include "rpc/streamed_send.h"

namespace gaps::rpc {

void encode_reference(const ReferenceView& view, v1::ReferenceView* out);
absl::StatusOr<ReferenceView> decode_reference(const v1::ReferenceView& view, const std::string& what);

// What an AdaptScene call asks: adapt to these views, as `adaptation` says (nullopt: the backend's options).
// With `exported` (Generator::export_adaptation of another worker) the worker installs it instead of adapting.
struct AdaptRequest {
  std::vector<ReferenceView> views;
  std::optional<SceneAdaptation> adaptation;
  std::string exported;
};

void encode_adapt_batch(const std::string& scene_id, const std::vector<ReferenceView>& views,
                        const std::optional<SceneAdaptation>& adaptation, v1::AdaptSceneBatch* out,
                        const std::string& exported = "");
absl::StatusOr<AdaptRequest> decode_adapt_batch(const v1::AdaptSceneBatch& batch);

// How a batch's tensors travel: `images` is the encoding of colour and alpha (renders, reference photos, the
// answer's images), `depths` that of the depth maps (kFloat32 or kFloat16; a map beyond half precision's range
// goes as float32 whatever this says); with an arena their payloads go into its shared region.
struct TensorTransfer {
  TensorEncoding images = TensorEncoding::kFloat32;
  SharedArena* arena = nullptr;
  TensorEncoding depths = TensorEncoding::kFloat32;
};

// The depth encoding that goes with an image encoding: float16 with bytes (compact) where the payload crosses a
// socket; float32 through shared memory (a copy costs less than converting there) and with float32 images (what an
// in-process backend sees, bit for bit).
TensorEncoding depth_encoding_for(TensorEncoding images, bool shared_memory);

// Shared-region bytes a batch needs in `images` encoding: its tensors (references once) and its answer. Depth maps
// are counted at float32's size, which holds them in any encoding.
struct SharedLayout {
  uint64_t request_bytes = 0;
  uint64_t answer_bytes = 0;
};
SharedLayout shared_layout(const std::vector<GenerationRequest>& requests, TensorEncoding images);

// Sets answer_encoding too. Fails only when the arena is full or kUint8 or kFloat16 meets a non-finite value.
// Given `parts`, the payloads are laid out but not converted, and *parts gets one part per pose and reference in
// the order they were laid out, for write_streamed (rpc/streamed_send.h), whose conversions report what kUint8
// refuses.
absl::Status encode_generation_batch(const std::vector<GenerationRequest>& requests, v1::GenerateBatch* out,
                                     const TensorTransfer& transfer = {}, std::vector<MessagePart>* parts = nullptr);
// Payloads in shared memory are read from `region` (the batch's shared_region, opened by the caller).
absl::StatusOr<std::vector<GenerationRequest>> decode_generation_batch(const v1::GenerateBatch& batch,
                                                                       const SharedRegion* region = nullptr);

// The answer's images in `transfer`'s encoding, into its arena when they all fit there, else into the
// message. kUint8 refuses non-finite pixels (INVALID_ARGUMENT naming the image). Given `parts`, as
// encode_generation_batch: one part per image, converted by write_streamed.
absl::Status encode_answer(const std::vector<at::Tensor>& images, const TensorTransfer& transfer,
                           v1::GenerateResult* out, std::vector<MessagePart>* parts = nullptr);

}  // namespace gaps::rpc

// What a diffusion worker decodes from the trainer: the first byte picks GenerateBatch or AdaptSceneBatch,
// the rest is the message. What decodes must encode and decode again to the same requests, in both hand-overs
// (float32; compact: bytes for colour and alpha, half precision for depth).
#include "fuzz/fuzz_support.h"
#include "rpc/generation_codec.h"

namespace {

void generate_batch(const uint8_t* data, size_t size) {
  gaps::v1::GenerateBatch batch;
  if (!batch.ParseFromArray(data, static_cast<int>(size))) return;
  const auto requests = gaps::rpc::decode_generation_batch(batch);
  if (!requests.ok()) return;
  for (const auto encoding : {gaps::rpc::TensorEncoding::kFloat32, gaps::rpc::TensorEncoding::kUint8}) {
    gaps::v1::GenerateBatch again;
    // Decoded tensors are finite, so neither encoding may refuse them.
    const gaps::rpc::TensorTransfer transfer{encoding, nullptr, gaps::rpc::depth_encoding_for(encoding, false)};
    if (!gaps::rpc::encode_generation_batch(*requests, &again, transfer).ok()) __builtin_trap();
    const auto back = gaps::rpc::decode_generation_batch(again);
    if (!back.ok() || back->size() != requests->size()) __builtin_trap();
  }
}

void adapt_batch(const uint8_t* data, size_t size) {
  gaps::v1::AdaptSceneBatch batch;
  if (!batch.ParseFromArray(data, static_cast<int>(size))) return;
  const auto adapt = gaps::rpc::decode_adapt_batch(batch);
  if (!adapt.ok()) return;
  gaps::v1::AdaptSceneBatch again;
  gaps::rpc::encode_adapt_batch(batch.scene_id(), adapt->views, adapt->adaptation, &again);
  const auto back = gaps::rpc::decode_adapt_batch(again);
  if (!back.ok() || back->views.size() != adapt->views.size()) __builtin_trap();
}

}  // namespace

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  if (size == 0) return 0;
  if (data[0] % 2 == 0)
    generate_batch(data + 1, size - 1);
  else
    adapt_batch(data + 1, size - 1);
  return 0;
}

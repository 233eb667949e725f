#pragma once
// Conversions between the project's types and the gaps.v1 messages, chunked transfer of large messages,
// and status mapping between absl and gRPC. Every decoder checks what it reads and names the offending
// item in its error, because the data comes from another process.
#include <algorithm>
#include <string>

#include <ATen/Tensor.h>
#include <google/protobuf/message.h>
#include <grpcpp/grpcpp.h>
#include "absl/status/statusor.h"
#include "gaps/v1/common.pb.h"
#include "gaps/v1/trainer.pb.h"
#include "gs_trainer/scene/camera.h"

namespace gaps::rpc {

class SharedArena;
class SharedRegion;

// Bytes per Chunk / file chunk message: well under gRPC's default 4 MiB message cap.
inline constexpr size_t kChunkBytes = 1 << 20;

// How a float tensor travels: RAW_F32, RAW_U8 for images and alpha maps in [0, 1], or RAW_F16 for depth maps.
enum class TensorEncoding { kFloat32, kUint8, kFloat16 };

// Largest magnitude a half-precision value holds.
inline constexpr float kHalfMax = 65504.0f;

// Float tensor (any shape, any device) -> RAW_F32 (any shape).
void encode_raw(const at::Tensor& tensor, v1::Tensor* out);
// Float tensor (any shape, any device) -> `encoding`, its payload in the message or, given an arena, in the
// arena's shared region (RESOURCE_EXHAUSTED when it is full). kUint8 and kFloat16 refuse NaN and infinite values
// (INVALID_ARGUMENT naming `what`); kUint8 clamps the rest to [0, 1]; kFloat16 rounds to nearest even and, when a
// magnitude exceeds kHalfMax, sends the tensor as RAW_F32 instead (the message says which), so that no value is
// lost. After an error `out` holds a partial encoding.
absl::Status encode_tensor(const at::Tensor& tensor, TensorEncoding encoding, SharedArena* arena,
                           const std::string& what, v1::Tensor* out);

// A payload laid out but not yet converted: its destination (in a message or a shared region) has its final
// size, so the message's size is known before the conversions run (rpc/streamed_send.h overlaps them with
// sending).
struct DeferredPayload {
  at::Tensor values;  // the tensor as given, or its float32 CPU copy where laying out needed the values
  TensorEncoding encoding = TensorEncoding::kFloat32;
  uint8_t* destination = nullptr;
  std::string what;
};
// As encode_tensor, but only lays the payload out (encoding, shape, a destination of the final size) and
// returns the conversion for fill_payload. Fails when the arena is full, and for kFloat16, whose size depends on
// the values, on NaN and infinite ones.
absl::StatusOr<DeferredPayload> lay_out_tensor(const at::Tensor& tensor, TensorEncoding encoding, SharedArena* arena,
                                               const std::string& what, v1::Tensor* out);
// Converts a laid-out payload into its destination: encode_tensor's second half, with its errors.
absl::Status fill_payload(const DeferredPayload& payload);
// The payload size of `tensor` in `encoding`.
uint64_t encoded_bytes(const at::Tensor& tensor, TensorEncoding encoding);
// RAW_F32 / unspecified -> kFloat32, RAW_U8 -> kUint8, RAW_F16 -> kFloat16; any other is INVALID_ARGUMENT naming
// `what`.
absl::StatusOr<TensorEncoding> tensor_encoding(v1::Tensor::Encoding encoding, const std::string& what);
v1::Tensor::Encoding to_proto(TensorEncoding encoding);
// H x W x 3 (or x 1) image in [0, 1] -> 8-bit PNG.
absl::Status encode_png(const at::Tensor& image, v1::Tensor* out);
// Any encoding -> float32 CPU tensor. `what` names the tensor in errors. PNG images decode to H x W x 3. A
// payload in shared memory is read from `region` (INVALID_ARGUMENT when there is none or the slice lies
// outside it).
absl::StatusOr<at::Tensor> decode_tensor(const v1::Tensor& tensor, const std::string& what,
                                         const SharedRegion* region = nullptr);
// As decode_tensor, also requiring the given shape (-1: any size in that dimension) and finite values.
absl::StatusOr<at::Tensor> decode_tensor_shaped(const v1::Tensor& tensor, const std::vector<int64_t>& shape,
                                                const std::string& what, const SharedRegion* region = nullptr);

void encode_camera(const Camera& camera, v1::Camera* out);
// Checks sizes, finiteness and that the rotation is orthonormal with determinant +1.
absl::StatusOr<Camera> decode_camera(const v1::Camera& camera, const std::string& what);

grpc::Status to_grpc(const absl::Status& status);
absl::Status from_grpc(const grpc::Status& status, const std::string& what);

// Sends `message` serialized as consecutive Chunks through `write` (returns false when the stream broke).
template <typename WriteFn>
bool write_chunked(const google::protobuf::Message& message, WriteFn&& write) {
  const std::string bytes = message.SerializeAsString();
  size_t offset = 0;
  do {
    v1::Chunk chunk;
    chunk.set_total_size(bytes.size());
    const size_t n = std::min(kChunkBytes, bytes.size() - offset);
    chunk.set_data(bytes.data() + offset, n);
    offset += n;
    if (!write(chunk)) return false;
  } while (offset < bytes.size());
  return true;
}

// Sends a file of SubmitJob as FileChunks of at most `chunk_bytes` through `write` (at least one, so empty
// files arrive too; returns false when the stream broke).
template <typename WriteFn>
bool write_file_chunks(v1::FileChunk::Kind kind, int index, const std::string& bytes, WriteFn&& write,
                       size_t chunk_bytes = kChunkBytes) {
  size_t offset = 0;
  do {
    v1::SubmitJobRequest request;
    v1::FileChunk* chunk = request.mutable_file();
    chunk->set_kind(kind);
    chunk->set_index(index);
    const size_t n = std::min(chunk_bytes, bytes.size() - offset);
    chunk->set_data(bytes.data() + offset, n);
    offset += n;
    chunk->set_last(offset == bytes.size());
    if (!write(request)) return false;
  } while (offset < bytes.size());
  return true;
}

// Reads Chunks through `read` (returns false at the end of the stream) until `total_size` bytes arrived,
// then parses them into `out`. Fails with RESOURCE_EXHAUSTED when the sender announces more than
// `max_bytes`, INVALID_ARGUMENT when sizes disagree or the bytes do not parse.
template <typename ReadFn>
absl::Status read_chunked(ReadFn&& read, uint64_t max_bytes, google::protobuf::Message* out) {
  std::string bytes;
  uint64_t total = 0;
  bool first = true;
  v1::Chunk chunk;
  while (read(&chunk)) {
    if (first) {
      total = chunk.total_size();
      if (total > max_bytes)
        return absl::ResourceExhaustedError("message of " + std::to_string(total) + " bytes exceeds the limit of " +
                                            std::to_string(max_bytes));
      bytes.reserve(total);
      first = false;
    }
    if (bytes.size() + chunk.data().size() > total)
      return absl::InvalidArgumentError("chunks exceed the announced size of " + std::to_string(total) + " bytes");
    bytes += chunk.data();
    if (bytes.size() == total) break;
  }
  if (first) return absl::InvalidArgumentError("stream ended before any chunk");
  if (bytes.size() != total)
    return absl::InvalidArgumentError("stream ended after " + std::to_string(bytes.size()) + " of " +
                                      std::to_string(total) + " bytes");
  if (!out->ParseFromString(bytes))
    return absl::InvalidArgumentError("chunks do not form a valid " + out->GetTypeName());
  return absl::OkStatus();
}

}  // namespace gaps::rpc

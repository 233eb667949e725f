#pragma once
// Sending a large message while its payloads are still being converted. A message is laid out first with every
// payload at its final size (lay_out_tensor), so its size is known for the first Chunk; then a thread converts
// the payloads part by part (a part is one top-level element of a repeated field: a pose, a reference view, an
// answer's image) while the caller's thread serialises each converted part and sends it. The rest of the message
// (its other fields) goes last, so that a caller may set values that are known only once the conversions ran,
// such as their time, as long as the size stays the same. The chunks' bytes are a valid serialization of the
// message (the format lets fields arrive in any order and merges repeated ones), so read_chunked is the receiver.
#include <functional>
#include <vector>

#include <google/protobuf/message.h>
#include "absl/status/status.h"
#include "gaps/v1/common.pb.h"
#include "rpc/codec.h"

namespace gaps::rpc {

// Element `index` of the repeated message field numbered `field` of a message, and the payloads it holds.
struct MessagePart {
  int field = 0;
  int index = 0;
  std::vector<DeferredPayload> payloads;
};

struct StreamedSendTimes {
  double convert_seconds = 0;  // the conversions, on their own thread, overlapping the sending
  double send_seconds = 0;     // the whole call: serialising and writing, waits for conversions included
};

// Sends `message`, laid out with `parts` (their payloads not yet converted; each a distinct element of a repeated
// message field, every element of those fields a part, in increasing index per field), as Chunks of at most
// kChunkBytes through `write`. Before the rest of the message is serialised, `finish` (when given) may change its
// fields, keeping its serialised size; it is told the conversions' seconds. Returns the first conversion's error
// (INVALID_ARGUMENT naming the tensor; the stream is then left incomplete, so the caller cancels the call),
// UNAVAILABLE when `write` returned false, INTERNAL when the parts do not cover those fields or `finish` changed
// the size.
absl::Status write_streamed(google::protobuf::Message& message, const std::vector<MessagePart>& parts,
                            const std::function<bool(const v1::Chunk&)>& write,
                            const std::function<void(double convert_seconds)>& finish = nullptr,
                            StreamedSendTimes* times = nullptr);

}  // namespace gaps::rpc

#pragma once
// Fuzz inputs that are streams of protobuf messages: each message is its varint length and its bytes
// (the delimited form protobuf's util/delimited_message_util writes), so libFuzzer can mutate
// the sequence and the fields alike.
#include <cstdint>
#include <string>
#include <vector>

#include <google/protobuf/io/coded_stream.h>
#include <google/protobuf/message_lite.h>

namespace gaps::fuzz {

// Parses up to `max_messages` messages; stops at the first that does not parse.
template <typename Message>
std::vector<Message> read_delimited(const uint8_t* data, size_t size, int max_messages) {
  google::protobuf::io::CodedInputStream in(data, static_cast<int>(size));
  std::vector<Message> messages;
  uint32_t length = 0;
  while (static_cast<int>(messages.size()) < max_messages && in.ReadVarint32(&length)) {
    const auto limit = in.PushLimit(static_cast<int>(length));
    Message m;
    if (!m.ParseFromCodedStream(&in) || !in.ConsumedEntireMessage()) break;
    in.PopLimit(limit);
    messages.push_back(std::move(m));
  }
  return messages;
}

inline void append_delimited(const google::protobuf::MessageLite& message, std::string* out) {
  const std::string bytes = message.SerializeAsString();
  uint32_t length = static_cast<uint32_t>(bytes.size());
  while (length >= 0x80) {
    out->push_back(static_cast<char>((length & 0x7f) | 0x80));
    length >>= 7;
  }
  out->push_back(static_cast<char>(length));
  *out += bytes;
}

}  // namespace gaps::fuzz

#include "rpc/streamed_send.h"

#include <chrono>
#include <condition_variable>
#include <map>
#include <mutex>
#include <string_view>
#include <thread>

#include "absl/strings/str_cat.h"
#include "common/status_macros.h"
#include "common/stopwatch.h"

namespace gaps::rpc {
namespace {

using google::protobuf::FieldDescriptor;
using google::protobuf::Message;

void append_varint(uint64_t value, std::string* out) {
  while (value >= 0x80) {
    out->push_back(static_cast<char>((value & 0x7f) | 0x80));
    value >>= 7;
  }
  out->push_back(static_cast<char>(value));
}

size_t varint_size(uint64_t value) {
  size_t n = 1;
  while (value >= 0x80) value >>= 7, ++n;
  return n;
}

uint64_t length_delimited_tag(int field) { return (static_cast<uint64_t>(field) << 3) | 2; }

// Bytes `element` takes as an element of field `field`: its tag, its length and itself.
size_t tagged_size(const Message& element, int field) {
  const size_t size = element.ByteSizeLong();
  return varint_size(length_delimited_tag(field)) + varint_size(size) + size;
}

std::string tagged(const Message& element, int field) {
  std::string out;
  append_varint(length_delimited_tag(field), &out);
  append_varint(element.ByteSizeLong(), &out);
  element.AppendToString(&out);
  return out;
}

// Cuts the bytes it is given into Chunks of at most kChunkBytes, each announcing the message's size.
class ChunkWriter {
 public:
  ChunkWriter(uint64_t total, const std::function<bool(const v1::Chunk&)>& write) : total_(total), write_(write) {}
  bool append(std::string_view bytes) {
    while (!bytes.empty()) {
      const size_t n = std::min(kChunkBytes - buffer_.size(), bytes.size());
      buffer_.append(bytes.data(), n);
      bytes.remove_prefix(n);
      appended_ += n;
      if (buffer_.size() == kChunkBytes && !flush()) return false;
    }
    return true;
  }
  // Sends what is left; at least one chunk goes, so that an empty message arrives too.
  bool finish() { return (buffer_.empty() && chunks_ > 0) || flush(); }
  uint64_t appended() const { return appended_; }

 private:
  bool flush() {
    v1::Chunk chunk;
    chunk.set_total_size(total_);
    chunk.set_data(std::move(buffer_));
    buffer_.clear();
    ++chunks_;
    return write_(chunk);
  }
  const uint64_t total_;
  const std::function<bool(const v1::Chunk&)>& write_;
  std::string buffer_;
  uint64_t appended_ = 0;
  int chunks_ = 0;
};

// The repeated fields the parts stand for, by number; INTERNAL when the parts do not match them.
absl::StatusOr<std::map<int, const FieldDescriptor*>> streamed_fields(const Message& message,
                                                                      const std::vector<MessagePart>& parts) {
  std::map<int, int> next_index;
  for (const MessagePart& part : parts) {
    int& next = next_index[part.field];
    if (part.index != next)
      return absl::InternalError(absl::StrCat("streamed parts of field ", part.field, " are out of order"));
    ++next;
  }
  std::map<int, const FieldDescriptor*> fields;
  for (const auto& [number, count] : next_index) {
    const FieldDescriptor* field = message.GetDescriptor()->FindFieldByNumber(number);
    if (field == nullptr || !field->is_repeated() || field->cpp_type() != FieldDescriptor::CPPTYPE_MESSAGE ||
        message.GetReflection()->FieldSize(message, field) != count)
      return absl::InternalError(
          absl::StrCat("streamed parts do not cover field ", number, " of ", message.GetTypeName()));
    fields[number] = field;
  }
  return fields;
}

// Runs the parts' conversions in order on a thread of its own; converted(i) waits until part i is done.
class Converter {
 public:
  explicit Converter(const std::vector<MessagePart>& parts) : parts_(parts), thread_([this] { run(); }) {}
  ~Converter() {
    {
      std::lock_guard<std::mutex> lock(mutex_);
      stop_ = true;
    }
    thread_.join();
  }
  // OK once part i is converted; the conversion's error when it (or an earlier one) failed.
  absl::Status converted(size_t i) {
    std::unique_lock<std::mutex> lock(mutex_);
    done_changed_.wait(lock, [&] { return done_ > i || !failure_.ok(); });
    return done_ > i ? absl::OkStatus() : failure_;
  }
  double seconds() {
    std::lock_guard<std::mutex> lock(mutex_);
    return seconds_;
  }

 private:
  void run() {
    auto clock = std::chrono::steady_clock::now();
    for (const MessagePart& part : parts_) {
      absl::Status st;
      for (const DeferredPayload& payload : part.payloads)
        if (st = fill_payload(payload); !st.ok()) break;
      std::lock_guard<std::mutex> lock(mutex_);
      seconds_ += lap_seconds(&clock);
      if (!st.ok())
        failure_ = st;
      else
        ++done_;
      done_changed_.notify_all();
      if (stop_ || !st.ok()) return;
    }
  }
  const std::vector<MessagePart>& parts_;
  std::mutex mutex_;
  std::condition_variable done_changed_;
  size_t done_ = 0;
  absl::Status failure_;
  bool stop_ = false;
  double seconds_ = 0;
  std::thread thread_;  // last: started once the members it uses exist
};

}  // namespace

absl::Status write_streamed(Message& message, const std::vector<MessagePart>& parts,
                            const std::function<bool(const v1::Chunk&)>& write,
                            const std::function<void(double)>& finish, StreamedSendTimes* times) {
  auto start = std::chrono::steady_clock::now();
  const absl::StatusOr<std::map<int, const FieldDescriptor*>> fields = streamed_fields(message, parts);
  if (!fields.ok()) return fields.status();
  const google::protobuf::Reflection& reflection = *message.GetReflection();
  const auto element = [&](const MessagePart& part) -> const Message& {
    return reflection.GetRepeatedMessage(message, fields->at(part.field), part.index);
  };
  const uint64_t total = message.ByteSizeLong();
  uint64_t rest = total;
  for (const MessagePart& part : parts) rest -= tagged_size(element(part), part.field);
  ChunkWriter writer(total, write);
  const absl::Status broke = absl::UnavailableError("the stream broke while sending");
  double convert_seconds = 0;
  {
    Converter converter(parts);
    for (size_t i = 0; i < parts.size(); ++i) {
      GAPS_RETURN_IF_ERROR(converter.converted(i));
      if (!writer.append(tagged(element(parts[i]), parts[i].field))) return broke;
    }
    convert_seconds = converter.seconds();
  }
  if (finish) finish(convert_seconds);
  // The rest of the message: its streamed fields moved aside while it is serialised.
  std::vector<const FieldDescriptor*> moved;
  for (const auto& [number, field] : *fields) moved.push_back(field);
  std::unique_ptr<Message> aside(message.New());
  reflection.SwapFields(&message, aside.get(), moved);
  const std::string tail = message.SerializeAsString();
  reflection.SwapFields(&message, aside.get(), moved);
  if (tail.size() != rest)
    return absl::InternalError(absl::StrCat("the rest of ", message.GetTypeName(), " changed size from ", rest, " to ",
                                            tail.size(), " bytes while it was being sent"));
  if (!writer.append(tail) || !writer.finish()) return broke;
  if (times != nullptr) *times = {convert_seconds, lap_seconds(&start)};
  return absl::OkStatus();
}

}  // namespace gaps::rpc

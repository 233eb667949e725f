// Sending a message while its payloads are converted (rpc/streamed_send.h): what arrives parses as the message
// encoded at once would, in chunks under the cap; a tensor the encoding refuses stops the stream naming it; a
// broken stream stops the conversions; values set at the end reach the receiver.
#include <cmath>
#include <string>
#include <vector>

#include <ATen/ATen.h>
#include <google/protobuf/util/message_differencer.h>
#include <gtest/gtest.h>

#include "rpc/codec.h"
#include "rpc/generation_codec.h"
#include "rpc/streamed_send.h"
#include "tests/camera_test_util.h"

namespace gaps {
namespace {

using rpc::TensorEncoding;

ReferenceView reference_at(double x, int width, int height) {
  const Camera c = test::camera_on_x_axis(x, width, height);
  return {c, at::rand({height, width, 3}), at::rand({height, width}) * 5 + 1, at::rand({height, width})};
}

// Three poses sharing two references (each sent once), `width` x `height` pixels.
std::vector<GenerationRequest> requests_of_size(int width, int height) {
  at::manual_seed(3);
  const std::vector<ReferenceView> refs = {reference_at(0.0, width, height), reference_at(0.5, width, height)};
  std::vector<GenerationRequest> out;
  for (double x : {0.1, 0.2, 0.3}) {
    GenerationRequest q;
    q.camera = test::camera_on_x_axis(x, width, height);
    q.render_rgb = at::rand({height, width, 3});
    q.render_depth = at::rand({height, width}) * 5 + 1;
    q.render_alpha = at::rand({height, width});
    q.strength = 0.3;
    q.control_scale = 0.8;
    q.seed = static_cast<uint64_t>(x * 10);
    q.references = x < 0.25 ? refs : std::vector<ReferenceView>{refs[1], refs[0]};
    out.push_back(std::move(q));
  }
  return out;
}

struct Sent {
  std::vector<v1::Chunk> chunks;
  absl::Status status;
};

// Streams `requests` in `transfer`'s encoding; `write_limit` chunks are accepted, then the stream breaks.
Sent stream_batch(const std::vector<GenerationRequest>& requests, const rpc::TensorTransfer& transfer,
                  v1::GenerateBatch* batch, size_t write_limit = 1u << 30) {
  std::vector<rpc::MessagePart> parts;
  Sent sent;
  sent.status = rpc::encode_generation_batch(requests, batch, transfer, &parts);
  if (!sent.status.ok()) return sent;
  batch->set_scene_handle("scene#1");
  sent.status = rpc::write_streamed(*batch, parts, [&](const v1::Chunk& c) {
    if (sent.chunks.size() == write_limit) return false;
    sent.chunks.push_back(c);
    return true;
  });
  return sent;
}

template <typename Message>
absl::Status reassemble(const std::vector<v1::Chunk>& chunks, Message* out) {
  size_t i = 0;
  return rpc::read_chunked(
      [&](v1::Chunk* c) {
        if (i == chunks.size()) return false;
        *c = chunks[i++];
        return true;
      },
      uint64_t{1} << 34, out);
}

void expect_equal_messages(const google::protobuf::Message& a, const google::protobuf::Message& b) {
  std::string difference;
  google::protobuf::util::MessageDifferencer differencer;
  differencer.ReportDifferencesToString(&difference);
  EXPECT_TRUE(differencer.Compare(a, b)) << difference;
}

TEST(StreamedSend, ABatchArrivesAsTheBatchEncodedAtOnce) {
  const std::vector<GenerationRequest> requests = requests_of_size(24, 18);
  for (const rpc::TensorTransfer transfer :
       {rpc::TensorTransfer{TensorEncoding::kFloat32, nullptr, TensorEncoding::kFloat32},
        rpc::TensorTransfer{TensorEncoding::kUint8, nullptr, TensorEncoding::kFloat16}}) {
    v1::GenerateBatch whole;
    ASSERT_TRUE(rpc::encode_generation_batch(requests, &whole, transfer).ok());
    whole.set_scene_handle("scene#1");
    v1::GenerateBatch streamed;
    const Sent sent = stream_batch(requests, transfer, &streamed);
    ASSERT_TRUE(sent.status.ok()) << sent.status;
    ASSERT_EQ(sent.chunks.size(), 1u);
    EXPECT_EQ(sent.chunks[0].total_size(), whole.ByteSizeLong());
    v1::GenerateBatch back;
    ASSERT_TRUE(reassemble(sent.chunks, &back).ok());
    EXPECT_EQ(back.references_size(), 2);
    expect_equal_messages(back, whole);
  }
}

TEST(StreamedSend, AMessageLargerThanAChunkArrivesInChunksUnderTheCap) {
  // Float32 at 400 x 300: each pose carries 2.4 MB, more than a chunk.
  const std::vector<GenerationRequest> requests = requests_of_size(400, 300);
  v1::GenerateBatch whole;
  ASSERT_TRUE(rpc::encode_generation_batch(requests, &whole).ok());
  whole.set_scene_handle("scene#1");
  v1::GenerateBatch streamed;
  const Sent sent = stream_batch(requests, {}, &streamed);
  ASSERT_TRUE(sent.status.ok()) << sent.status;
  uint64_t bytes = 0;
  for (const v1::Chunk& c : sent.chunks) {
    EXPECT_LE(c.data().size(), rpc::kChunkBytes);
    EXPECT_EQ(c.total_size(), whole.ByteSizeLong());
    bytes += c.data().size();
  }
  EXPECT_GT(sent.chunks.size(), 10u);
  EXPECT_EQ(bytes, whole.ByteSizeLong());
  v1::GenerateBatch back;
  ASSERT_TRUE(reassemble(sent.chunks, &back).ok());
  expect_equal_messages(back, whole);
  auto decoded = rpc::decode_generation_batch(back);
  ASSERT_TRUE(decoded.ok()) << decoded.status();
  EXPECT_TRUE(at::equal((*decoded)[2].render_rgb, requests[2].render_rgb));
}

TEST(StreamedSend, ANonFiniteRenderStopsTheStreamNamingIt) {
  std::vector<GenerationRequest> requests = requests_of_size(400, 300);
  requests[2].render_rgb[5][7][1] = NAN;
  v1::GenerateBatch batch;
  const Sent sent = stream_batch(requests, {TensorEncoding::kUint8, nullptr, TensorEncoding::kFloat16}, &batch);
  EXPECT_EQ(sent.status.code(), absl::StatusCode::kInvalidArgument);
  EXPECT_NE(sent.status.message().find("pose 2 render_rgb"), std::string::npos) << sent.status;
  uint64_t bytes = 0;
  for (const v1::Chunk& c : sent.chunks) bytes += c.data().size();
  ASSERT_FALSE(sent.chunks.empty()) << "the poses before it were sent";
  EXPECT_LT(bytes, sent.chunks[0].total_size());
  v1::GenerateBatch back;
  EXPECT_FALSE(reassemble(sent.chunks, &back).ok()) << "an incomplete stream does not parse";

  // Half precision's size depends on the values, so a non-finite depth is refused while laying out.
  requests = requests_of_size(24, 18);
  requests[1].render_depth[0][0] = INFINITY;
  v1::GenerateBatch refused;
  const Sent laid_out = stream_batch(requests, {TensorEncoding::kUint8, nullptr, TensorEncoding::kFloat16}, &refused);
  EXPECT_EQ(laid_out.status.code(), absl::StatusCode::kInvalidArgument);
  EXPECT_NE(laid_out.status.message().find("pose 1 render_depth"), std::string::npos) << laid_out.status;
}

TEST(StreamedSend, ABrokenStreamStopsTheSending) {
  v1::GenerateBatch batch;
  const Sent sent = stream_batch(requests_of_size(400, 300), {}, &batch, 2);
  EXPECT_EQ(sent.status.code(), absl::StatusCode::kUnavailable) << sent.status;
  EXPECT_EQ(sent.chunks.size(), 2u);
}

TEST(StreamedSend, TheAnswerCarriesWhatItsFinishSetAndRefusesASizeChange) {
  at::manual_seed(5);
  const std::vector<at::Tensor> images = {at::rand({18, 24, 3}), at::rand({18, 24, 3})};
  for (const bool keep_size : {true, false}) {
    v1::GenerateResult result;
    std::vector<rpc::MessagePart> parts;
    ASSERT_TRUE(rpc::encode_answer(images, {TensorEncoding::kUint8}, &result, &parts).ok());
    ASSERT_EQ(parts.size(), 2u);
    result.add_notes("a note");
    (*result.mutable_transfer_seconds())["worker_encode"] = -1.0;
    std::vector<v1::Chunk> chunks;
    const absl::Status st = rpc::write_streamed(
        result, parts,
        [&](const v1::Chunk& c) {
          chunks.push_back(c);
          return true;
        },
        [&](double convert_seconds) {
          EXPECT_GE(convert_seconds, 0.0);
          (*result.mutable_transfer_seconds())["worker_encode"] = 0.25;
          if (!keep_size) result.add_notes("one more");
        });
    if (!keep_size) {
      EXPECT_EQ(st.code(), absl::StatusCode::kInternal) << st;
      continue;
    }
    ASSERT_TRUE(st.ok()) << st;
    v1::GenerateResult back;
    ASSERT_TRUE(reassemble(chunks, &back).ok());
    EXPECT_EQ(back.transfer_seconds().at("worker_encode"), 0.25);
    ASSERT_EQ(back.notes_size(), 1);
    ASSERT_EQ(back.images_size(), 2);
    auto image = rpc::decode_tensor_shaped(back.images(1), {18, 24, 3}, "image 1");
    ASSERT_TRUE(image.ok()) << image.status();
    EXPECT_LE((*image - images[1]).abs().max().item<float>(), 0.5f / 255 + 1e-6f);
  }
}

TEST(StreamedSend, PartsThatDoNotCoverTheirFieldAreRefused) {
  at::manual_seed(6);
  v1::GenerateResult result;
  std::vector<rpc::MessagePart> parts;
  ASSERT_TRUE(rpc::encode_answer({at::rand({4, 4, 3}), at::rand({4, 4, 3})}, {}, &result, &parts).ok());
  parts.pop_back();
  int writes = 0;
  const absl::Status st = rpc::write_streamed(result, parts, [&](const v1::Chunk&) { return ++writes > 0; });
  EXPECT_EQ(st.code(), absl::StatusCode::kInternal) << st;
  EXPECT_EQ(writes, 0);
}

}  // namespace
}  // namespace gaps

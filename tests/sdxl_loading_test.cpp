// The safetensors reader, the diffusers folder reader and the name -> tensor loader's errors.
#include <ATen/ATen.h>
#include <gtest/gtest.h>

#include "common/safetensors.h"
#include "diffusion_worker/sdxl/model_folder.h"
#include "diffusion_worker/sdxl/weights.h"
#include "tests/sdxl_test_util.h"
#include "tests/test_util.h"

namespace gaps::sdxl {
namespace {

using test::contains_all;

class SafetensorsTest : public test::TempDirTest {};

std::string header_file(const std::string& json, size_t data_bytes) {
  std::string bytes(8, '\0');
  for (int i = 0; i < 8; ++i) bytes[i] = static_cast<char>((json.size() >> (8 * i)) & 0xff);
  return bytes + json + std::string(data_bytes, '\0');
}

TEST_F(SafetensorsTest, RoundTripsFloatTypes) {
  TensorMap tensors{{"a.f32", at::randn({2, 3})},
                    {"b.f16", at::randn({4}).to(at::kHalf)},
                    {"c.bf16", at::randn({3, 1, 2}).to(at::kBFloat16)},
                    {"d.i64", at::arange(5)}};
  const std::string path = (dir_ / "t.safetensors").string();
  ASSERT_TRUE(write_safetensors(path, tensors).ok());
  auto read = read_safetensors(path);
  ASSERT_TRUE(read.ok()) << read.status();
  ASSERT_EQ(read->size(), tensors.size());
  for (const auto& [name, t] : tensors) {
    ASSERT_EQ(read->at(name).scalar_type(), t.scalar_type()) << name;
    EXPECT_TRUE(at::equal(read->at(name), t)) << name;
  }
}

TEST_F(SafetensorsTest, RejectsBadHeadersNamingFileAndTensor) {
  const auto error_of = [&](const std::string& bytes) {
    const auto path = write("bad.safetensors", bytes);
    auto r = read_safetensors(path.string());
    EXPECT_FALSE(r.ok());
    return std::string(r.status().message());
  };
  EXPECT_TRUE(contains_all(error_of("abc"), {"shorter than the 8-byte header length"}));
  EXPECT_TRUE(contains_all(error_of(header_file("{not json", 0)), {"not valid JSON"}));
  EXPECT_TRUE(contains_all(error_of(header_file(R"({"w":{"dtype":"F8_E4M3","shape":[1],"data_offsets":[0,1]}})", 1)),
                           {"bad.safetensors", "tensor 'w'", "unsupported dtype"}));
  EXPECT_TRUE(contains_all(error_of(header_file(R"({"w":{"dtype":"F32","shape":[2],"data_offsets":[0,4]}})", 8)),
                           {"tensor 'w'", "need 8"}));
  EXPECT_TRUE(contains_all(error_of(header_file(R"({"w":{"dtype":"F32","shape":[4],"data_offsets":[0,16]}})", 8)),
                           {"tensor 'w'", "outside the data section"}));
  std::string huge(8, '\xff');
  EXPECT_TRUE(contains_all(error_of(huge + "{}"), {"exceeds the file"}));
  EXPECT_FALSE(read_safetensors((dir_ / "absent.safetensors").string()).ok());
}

// In memory (what one worker hands another): the same bytes as the file, and the same checks on what it reads.
TEST_F(SafetensorsTest, EncodesTheFilesBytesAndDecodesThemWithTheirMetadata) {
  const TensorMap tensors{{"a", at::randn({3, 2})}, {"b", at::arange(7).to(at::kHalf)}};
  const SafetensorsMetadata metadata{{"format", "pt"}, {"note", "x"}};
  auto bytes = encode_safetensors(tensors, metadata);
  ASSERT_TRUE(bytes.ok()) << bytes.status();
  const std::string path = (dir_ / "t.safetensors").string();
  ASSERT_TRUE(write_safetensors(path, tensors, metadata).ok());
  EXPECT_EQ(test::read_text(path), *bytes);
  auto decoded = decode_safetensors(*bytes, "adapters from worker a");
  ASSERT_TRUE(decoded.ok()) << decoded.status();
  EXPECT_EQ(decoded->metadata, metadata);
  ASSERT_EQ(decoded->tensors.size(), 2u);
  for (const auto& [name, t] : tensors) EXPECT_TRUE(at::equal(decoded->tensors.at(name), t)) << name;
  const auto error_of = [](const std::string& b) {
    auto r = decode_safetensors(b, "adapters from worker a");
    EXPECT_FALSE(r.ok());
    return std::string(r.status().message());
  };
  EXPECT_TRUE(contains_all(error_of("abc"), {"adapters from worker a", "shorter than the 8-byte header length"}));
  EXPECT_TRUE(contains_all(error_of(bytes->substr(0, bytes->size() - 4)), {"tensor 'b'", "outside the data section"}));
  EXPECT_TRUE(contains_all(error_of(header_file(R"({"__metadata__":{"k":1}})", 0)), {"'k' is not a string"}));
}

TEST(WeightLoaderTest, NamesMissingMisshapedAndUnexpectedTensors) {
  WeightLoader w("unit (test)", {{"a", at::zeros({2, 3})}, {"b", at::zeros({4})}, {"extra.weight", at::zeros({1})}},
                 at::TensorOptions());
  EXPECT_EQ(w.take("a", {2, 3}).sizes(), at::IntArrayRef({2, 3}));
  w.take("b", {5});
  w.take("c", {7});
  const absl::Status s = w.finish();
  ASSERT_FALSE(s.ok());
  EXPECT_TRUE(contains_all(
      std::string(s.message()),
      {"unit (test)", "1 missing: c [7]", "b (checkpoint [4], config expects [5])", "1 unexpected: extra.weight"}));
}

TEST(WeightLoaderTest, ConvertsToTheRequestedDtype) {
  WeightLoader w("unit", {{"a", at::ones({2}, at::kHalf)}}, at::TensorOptions().dtype(at::kFloat));
  EXPECT_EQ(w.take("a", {2}).scalar_type(), at::kFloat);
  EXPECT_TRUE(w.finish().ok());
}

TEST(WeightLoaderTest, GivesConvolutionKernelsTheRequestedMemoryFormat) {
  const auto options = at::TensorOptions().dtype(at::kFloat).memory_format(at::MemoryFormat::ChannelsLast);
  WeightLoader w("unit", {{"kernel", at::rand({4, 3, 2, 2})}, {"bias", at::rand({4})}}, options);
  const at::Tensor kernel = w.take("kernel", {4, 3, 2, 2});
  EXPECT_TRUE(kernel.is_contiguous(at::MemoryFormat::ChannelsLast));
  EXPECT_FALSE(kernel.is_contiguous());
  EXPECT_TRUE(w.take("bias", {4}).is_contiguous());  // other ranks have no channels-last order
  const at::Tensor missing = w.take("missing", {5});
  EXPECT_EQ(missing.sizes(), at::IntArrayRef({5}));
  EXPECT_FALSE(w.finish().ok());
}

TEST(ModelFolderTest, ReadsTheTinySdxlFolder) {
  auto folder = ModelFolder::open(test::sdxl_model_dir());
  ASSERT_TRUE(folder.ok()) << folder.status();
  EXPECT_EQ(*folder->component_class("unet"), "UNet2DConditionModel");
  EXPECT_EQ(*folder->component_class("text_encoder_2"), "CLIPTextModelWithProjection");
  auto config = folder->read_json("vae");
  ASSERT_TRUE(config.ok());
  EXPECT_DOUBLE_EQ((*config)["scaling_factor"].get<double>(), 0.13025);
  auto weights = folder->read_weights("vae");
  ASSERT_TRUE(weights.ok()) << weights.status();
  EXPECT_TRUE(weights->count("decoder.conv_out.weight"));
  EXPECT_FALSE(folder->component_class("controlnet").ok());
  EXPECT_FALSE(folder->read_weights("vae", "fp16").ok());
  EXPECT_FALSE(ModelFolder::open(test::sdxl_model_dir() + "/absent").ok());
}

}  // namespace
}  // namespace gaps::sdxl

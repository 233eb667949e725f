// LPIPS-VGG and the torch checkpoint reader.
//
// Parity: tests/scripts/lpips_reference.py builds a torchvision VGG16 with random weights, saves it
// as zip and legacy checkpoints and scores image pairs with PyPI's `lpips` package; the C++ metric
// must agree on both files. The real v0.1 linear weights come from GAPS_DATA_DIR/lpips/vgg.pth.
#include "gs_trainer/eval/lpips.h"

#include <ATen/ATen.h>
#include <ATen/core/grad_mode.h>
#include <gtest/gtest.h>
#include <unistd.h>

#include <cmath>
#include <cstdio>
#include <cstring>
#include <fstream>
#include <functional>
#include <map>
#include <nlohmann/json.hpp>
#include <string>
#include <utility>
#include <vector>

#include "common/torch_pickle.h"
#include "gs_trainer/eval/metrics.h"

#include "common/io_util.h"
#include "common/safetensors.h"
#include "tests/lpips_real_weights.h"
#include "tests/lpips_test_util.h"
#include "tests/test_util.h"

namespace gaps {
namespace {

using test::kLinWeights;
using test::make_temp_dir;
using test::read_file;

// The LPIPS v0.1 linear weights come with the benchmark data (GAPS_DATA_DIR), which is never committed.
#define REQUIRE_LIN_WEIGHTS()                 \
  if (access(kLinWeights.c_str(), R_OK) != 0) \
  GTEST_SKIP() << kLinWeights << " is missing (benchmark data not found at GAPS_DATA_DIR)"

// ---- small file helpers ----

void write_file(const std::string& path, const std::string& bytes) {
  std::ofstream(path, std::ios::binary | std::ios::trunc).write(bytes.data(), bytes.size());
}

bool contains(absl::string_view haystack, absl::string_view needle) {
  return haystack.find(needle) != absl::string_view::npos;
}

// A scratch folder for one test's hand-made files.
class ScratchDir {
 public:
  ScratchDir() : path_(make_temp_dir("gaps_lpips_scratch")) {}
  ~ScratchDir() { remove_tree(path_); }
  std::string file(const std::string& name) const { return path_ + "/" + name; }

 private:
  std::string path_;
};

// ---------------------------------------------------------------------------------------------
// The shipped v0.1 linear weights (legacy pickle) and corrupt variants of it.

TEST(LinWeights, V01VggFileHasFiveNonNegativeTaps) {
  REQUIRE_LIN_WEIGHTS();
  auto dict = load_torch_state_dict(kLinWeights);
  ASSERT_TRUE(dict.ok()) << dict.status();
  const std::vector<int64_t> channels = {64, 128, 256, 512, 512};
  ASSERT_EQ(dict->size(), channels.size());
  for (size_t tap = 0; tap < channels.size(); ++tap) {
    const std::string key = "lin" + std::to_string(tap) + ".model.1.weight";
    ASSERT_EQ(dict->count(key), 1u) << key;
    const at::Tensor& w = dict->at(key);
    EXPECT_EQ(w.scalar_type(), at::kFloat) << key;
    EXPECT_EQ(w.sizes(), at::IntArrayRef({1, channels[tap], 1, 1})) << key;
    EXPECT_GE(w.min().item<float>(), 0.0f) << key;  // LPIPS clamps its linear weights at >= 0
    EXPECT_GT(w.max().item<float>(), 0.0f) << key;
  }
}

TEST(TorchPickle, MissingAndEmptyFiles) {
  auto missing = load_torch_state_dict("/nonexistent/weights.pth");
  EXPECT_EQ(missing.status().code(), absl::StatusCode::kNotFound);
  EXPECT_TRUE(contains(missing.status().message(), "/nonexistent/weights.pth"));
  ScratchDir dir;
  write_file(dir.file("empty.pth"), "");
  auto empty = load_torch_state_dict(dir.file("empty.pth"));
  EXPECT_FALSE(empty.ok());
  EXPECT_TRUE(contains(empty.status().message(), "empty")) << empty.status();
}

TEST(TorchPickle, EveryTruncationOfALegacyFileFails) {
  REQUIRE_LIN_WEIGHTS();
  const std::string bytes = read_file(kLinWeights);
  ASSERT_GT(bytes.size(), 1000u);
  ScratchDir dir;
  const std::string path = dir.file("truncated.pth");
  for (size_t length = 1; length < bytes.size(); ++length) {
    write_file(path, bytes.substr(0, length));
    auto dict = load_torch_state_dict(path);
    ASSERT_FALSE(dict.ok()) << "accepted " << length << " of " << bytes.size() << " bytes";
    ASSERT_TRUE(contains(dict.status().message(), path)) << dict.status();
  }
  // Cut inside the last storage's bytes: a truncation error, not a parse error.
  write_file(path, bytes.substr(0, bytes.size() - 10));
  auto cut = load_torch_state_dict(path);
  EXPECT_EQ(cut.status().code(), absl::StatusCode::kDataLoss) << cut.status();
  EXPECT_TRUE(contains(cut.status().message(), "truncated")) << cut.status();
}

TEST(TorchPickle, GarbageIsNotMistakenForACheckpoint) {
  ScratchDir dir;
  const std::vector<std::pair<std::string, std::string>> cases = {
      {"text.pth", "this is not a checkpoint\n"},
      {"binary.pth", std::string("\x80\x02\x8a\x0a\x00\x01\x02\x03\x04\x05\x06\x07\x08\x09.", 15)},
      {"fake_zip.pth", std::string("PK\x03\x04", 4) + std::string(200, 'x')}};
  for (const auto& [name, bytes] : cases) {
    write_file(dir.file(name), bytes);
    auto dict = load_torch_state_dict(dir.file(name));
    EXPECT_FALSE(dict.ok()) << name;
    EXPECT_TRUE(contains(dict.status().message(), dir.file(name))) << dict.status();
  }
  auto magic = load_torch_state_dict(dir.file("binary.pth"));
  EXPECT_TRUE(contains(magic.status().message(), "magic number")) << magic.status();
}

TEST(TorchPickle, CorruptOpcodeIsReported) {
  REQUIRE_LIN_WEIGHTS();
  std::string bytes = read_file(kLinWeights);
  const size_t global = bytes.find("ccollections\nOrderedDict");
  ASSERT_NE(global, std::string::npos);
  bytes[global] = '\xff';
  ScratchDir dir;
  write_file(dir.file("opcode.pth"), bytes);
  auto dict = load_torch_state_dict(dir.file("opcode.pth"));
  ASSERT_FALSE(dict.ok());
  EXPECT_TRUE(contains(dict.status().message(), "unsupported pickle opcode 0xff")) << dict.status();
  EXPECT_TRUE(contains(dict.status().message(), "main pickle")) << dict.status();
}

// A dict made a key of itself (found by fuzz/torch_pickle_fuzz.cpp: the objects, shared pointers, were never
// freed) is refused by name; fuzz/regressions/torch_pickle holds the fuzzer's inputs.
TEST(TorchPickle, AContainerPutInsideItselfIsRefused) {
  ScratchDir dir;
  write_file(dir.file("cycle.pth"), "}}}2}ss}M");  // EMPTY_DICT x3, DUP, EMPTY_DICT, SETITEM: d[d] = {}
  auto dict = load_torch_state_dict(dir.file("cycle.pth"));
  ASSERT_FALSE(dict.ok());
  EXPECT_TRUE(contains(dict.status().message(), "SETITEM would put a dict inside itself (a cycle)")) << dict.status();
}

TEST(TorchPickle, StorageSizeMismatchIsReported) {
  REQUIRE_LIN_WEIGHTS();
  std::string bytes = read_file(kLinWeights);
  // The file ends with the five float storages (64 + 128 + 256 + 512 + 512 elements), each as an
  // int64 element count followed by the data; the first count sits this far from the end.
  const size_t count_at = bytes.size() - (5 * 8 + 4 * (64 + 128 + 256 + 512 + 512));
  int64_t count = 0;
  std::memcpy(&count, bytes.data() + count_at, sizeof count);
  ASSERT_TRUE(count == 64 || count == 128 || count == 256 || count == 512) << count;
  const int64_t wrong = count + 1;
  std::memcpy(bytes.data() + count_at, &wrong, sizeof wrong);
  ScratchDir dir;
  write_file(dir.file("count.pth"), bytes);
  auto dict = load_torch_state_dict(dir.file("count.pth"));
  ASSERT_FALSE(dict.ok());
  const std::string expected =
      std::to_string(wrong) + " elements in the data section, " + std::to_string(count) + " in the pickle";
  EXPECT_TRUE(contains(dict.status().message(), expected)) << dict.status();
}

// ---------------------------------------------------------------------------------------------
// Fixtures from Python (tests/lpips_test_util.h; the CUDA parity test is in gpu/).
using TorchPickleFixtures = test::PythonFixtures;
using LpipsParity = test::PythonFixtures;

void expect_tensor(const std::map<std::string, at::Tensor>& dict, const std::string& key, const at::Tensor& expected,
                   const std::string& file) {
  ASSERT_EQ(dict.count(key), 1u) << key << " in " << file;
  const at::Tensor& t = dict.at(key);
  EXPECT_EQ(t.scalar_type(), expected.scalar_type()) << key << " in " << file;
  EXPECT_EQ(t.sizes(), expected.sizes()) << key << " in " << file;
  EXPECT_TRUE(t.is_contiguous()) << key << " in " << file;
  EXPECT_TRUE(t.sizes() == expected.sizes() && at::equal(t, expected)) << key << " in " << file;
}

TEST_F(TorchPickleFixtures, ReadsViewsSharedStoragesAndDtypes) {
  at::Tensor whole = at::arange(60, at::kDouble).reshape({5, 12});
  const std::map<std::string, at::Tensor> expected = {
      {"whole", whole},
      {"column", whole.select(1, 3)},
      {"transposed", whole.t()},
      {"block", whole.slice(0, 1, 4).slice(1, 2, 9, 3)},
      {"half", at::arange(6, at::kHalf).reshape({2, 3})},
      {"bfloat16", at::arange(4, at::kBFloat16)},
      {"int64", at::arange(-3, 3, at::kLong)},
      {"int32", at::arange(-3, 3, at::kInt)},
      {"uint8", at::arange(250, 256, at::kByte)},
      {"bool", at::tensor({1, 0, 1}, at::kInt).to(at::kBool)},
      {"scalar", at::scalar_tensor(2.5, at::kFloat)},
      {"empty", at::zeros({0, 3}, at::kFloat)},
      {"channels_last", at::arange(24, at::kFloat).reshape({1, 2, 3, 4})}};
  for (const char* file : {"protocol2_zip", "protocol2_legacy", "protocol4_zip", "protocol4_legacy"}) {
    const std::string name = manifest_["pickles"][file].get<std::string>();
    auto dict = load_torch_state_dict(path(name));
    ASSERT_TRUE(dict.ok()) << dict.status();
    EXPECT_EQ(dict->size(), expected.size()) << name;
    for (const auto& [key, value] : expected) expect_tensor(*dict, key, value, name);
    // Views come back as independent copies.
    dict->at("column").fill_(-1);
    EXPECT_EQ(dict->at("whole")[0][3].item<double>(), 3.0) << name;
  }
}

TEST_F(TorchPickleFixtures, NonTensorEntryIsNamed) {
  const std::string file = path(manifest_["pickles"]["not_state_dict"].get<std::string>());
  auto dict = load_torch_state_dict(file);
  ASSERT_FALSE(dict.ok());
  EXPECT_TRUE(contains(dict.status().message(), "entry 'epoch' is not a tensor (found int)")) << dict.status();
}

TEST_F(TorchPickleFixtures, ZipAndLegacyBackbonesAgreeAndTruncationsFail) {
  auto zip = load_torch_state_dict(backbone("zip"));
  auto legacy = load_torch_state_dict(backbone("legacy"));
  ASSERT_TRUE(zip.ok()) << zip.status();
  ASSERT_TRUE(legacy.ok()) << legacy.status();
  EXPECT_EQ(zip->size(), 27u);  // 13 convolutions x (weight, bias) + classifier.6.bias
  ASSERT_EQ(zip->size(), legacy->size());
  for (const auto& [key, tensor] : *zip) {
    ASSERT_EQ(legacy->count(key), 1u) << key;
    EXPECT_TRUE(at::equal(tensor, legacy->at(key))) << key;
  }
  EXPECT_EQ(zip->at("features.28.weight").sizes(), at::IntArrayRef({512, 512, 3, 3}));
  for (const char* format : {"zip", "legacy"}) {
    const std::string bytes = read_file(backbone(format));
    const std::string cut = path(std::string("cut_") + format + ".pth");
    for (size_t length : {size_t{100}, bytes.size() / 2, bytes.size() - 1}) {
      write_file(cut, bytes.substr(0, length));
      auto dict = load_torch_state_dict(cut);
      EXPECT_EQ(dict.status().code(), absl::StatusCode::kDataLoss)
          << format << " cut at " << length << ": " << dict.status();
      EXPECT_TRUE(contains(dict.status().message(), cut)) << dict.status();
    }
  }
}

class LpipsParityByFormat : public test::PythonFixtures, public ::testing::WithParamInterface<const char*> {};

TEST_P(LpipsParityByFormat, MatchesPythonLpipsOnRandomBackbone) {
  Lpips lpips = load_lpips(GetParam());
  at::NoGradGuard no_grad;
  ASSERT_GE(manifest_["pairs"].size(), 4u);
  for (const nlohmann::json& pair : manifest_["pairs"]) {
    const double expected = pair["distance"].get<double>();
    const double actual = lpips.distance(read_image(pair, "a"), read_image(pair, "b")).item<double>();
    EXPECT_NEAR(actual, expected, 1e-5 * std::abs(expected) + 1e-9)
        << pair["height"] << "x" << pair["width"] << " pair from the " << GetParam() << " file";
  }
}

INSTANTIATE_TEST_SUITE_P(BothFormats, LpipsParityByFormat, ::testing::Values("zip", "legacy"));

TEST_F(LpipsParity, IdenticalImagesAreZeroAndDistanceIsSymmetric) {
  Lpips lpips = load_lpips("zip");
  at::NoGradGuard no_grad;
  const nlohmann::json& pair = manifest_["pairs"][0];
  at::Tensor a = read_image(pair, "a"), b = read_image(pair, "b");
  EXPECT_EQ(lpips.distance(a, a).item<double>(), 0.0);
  EXPECT_NEAR(lpips.distance(a, b).item<double>(), lpips.distance(b, a).item<double>(), 1e-6);
  EXPECT_THROW(lpips.distance(a.slice(0, 0, 15), b.slice(0, 0, 15)), c10::Error);  // < 16 rows
  EXPECT_THROW(lpips.distance(a, b.slice(0, 0, 20)), c10::Error);
}

TEST_F(LpipsParity, EvaluateImageReportsLpips) {
  Lpips lpips = load_lpips("legacy");
  const nlohmann::json& pair = manifest_["pairs"][1];
  ImageMetrics m = evaluate_image(read_image(pair, "a"), read_image(pair, "b"), &lpips);
  ASSERT_TRUE(m.lpips.has_value());
  EXPECT_NEAR(*m.lpips, pair["distance"].get<double>(), 1e-5 * pair["distance"].get<double>());
  EXPECT_NEAR(m.psnr, psnr(read_image(pair, "a"), read_image(pair, "b")), 1e-12);
}

TEST_F(LpipsParity, BrokenBackbonesNameTheKey) {
  for (const char* kind : {"missing", "shape", "extra"}) {
    const nlohmann::json& bad = manifest_["bad_backbones"][kind];
    const std::string file = path(bad["file"].get<std::string>());
    auto lpips = Lpips::load(kLinWeights, file);
    ASSERT_FALSE(lpips.ok()) << kind;
    EXPECT_EQ(lpips.status().code(), absl::StatusCode::kInvalidArgument) << lpips.status();
    EXPECT_TRUE(contains(lpips.status().message(), bad["key"].get<std::string>())) << lpips.status();
    EXPECT_TRUE(contains(lpips.status().message(), file)) << lpips.status();
  }
  auto shape = Lpips::load(kLinWeights, path(manifest_["bad_backbones"]["shape"]["file"].get<std::string>()));
  EXPECT_TRUE(contains(shape.status().message(), "[256,128,5,5], expected [256,128,3,3]")) << shape.status();
  // A backbone given as the linear-weights file: the first lin key is missing.
  auto swapped = Lpips::load(backbone("zip"), backbone("zip"));
  EXPECT_TRUE(contains(swapped.status().message(), "missing key lin0.model.1.weight")) << swapped.status();
  auto absent = Lpips::load(kLinWeights, path("no_such_backbone.pth"));
  EXPECT_EQ(absent.status().code(), absl::StatusCode::kNotFound) << absent.status();
}

// ---------------------------------------------------------------------------------------------
// The set-up's real weights (scripts/lpips_weights.py) in one safetensors file.

using LpipsRealWeights = test::TempDirTest;

TEST_F(LpipsRealWeights, FernRunReportsLpipsAndMatchesPypiLpips) { test::check_fern_run_lpips(dir_, "cpu"); }

TEST_F(LpipsRealWeights, TheSetUpFileLoadsWithEveryLayer) {
  const std::string weights = default_lpips_weights_path().string();
  absl::StatusOr<sdxl::TensorMap> tensors = sdxl::read_safetensors(weights);
  ASSERT_TRUE(tensors.ok()) << tensors.status() << " (bash scripts/setup.sh makes the file)";
  EXPECT_EQ(tensors->size(), 13u * 2 + 5);  // 13 convolutions (weight, bias) and 5 heads
  EXPECT_EQ(tensors->at("features.28.weight").sizes(), at::IntArrayRef({512, 512, 3, 3}));
  EXPECT_TRUE(Lpips::load_safetensors(weights).ok());
}

// A small stand-in of the set-up's file, with `edit` applied: every check of load_safetensors is reached.
std::string write_weights(const std::filesystem::path& dir, const std::function<void(sdxl::TensorMap&)>& edit,
                          const std::string& format = "gaps-lpips-vgg16-v0.1") {
  sdxl::TensorMap tensors;
  const int64_t channels[5] = {64, 128, 256, 512, 512};
  const int convs[5] = {2, 2, 3, 3, 3};
  int index = 0;
  int64_t in = 3;
  for (int block = 0; block < 5; ++block) {
    if (block > 0) ++index;
    for (int i = 0; i < convs[block]; ++i, index += 2) {
      tensors["features." + std::to_string(index) + ".weight"] = at::zeros({channels[block], in, 3, 3});
      tensors["features." + std::to_string(index) + ".bias"] = at::zeros({channels[block]});
      in = channels[block];
    }
    tensors["lin" + std::to_string(block) + ".model.1.weight"] = at::zeros({1, channels[block], 1, 1});
  }
  edit(tensors);
  const std::string path = (dir / "weights.safetensors").string();
  EXPECT_TRUE(sdxl::write_safetensors(path, tensors, {{"format", format}}).ok());
  return path;
}

TEST_F(LpipsRealWeights, BrokenFilesAreRefusedByName) {
  const auto none = [](sdxl::TensorMap&) {};
  EXPECT_TRUE(Lpips::load_safetensors(write_weights(dir_, none)).ok());

  const absl::StatusOr<Lpips> absent = Lpips::load_safetensors((dir_ / "absent.safetensors").string());
  EXPECT_EQ(absent.status().code(), absl::StatusCode::kNotFound);
  EXPECT_TRUE(contains(absent.status().message(), "scripts/setup.sh")) << absent.status();

  const absl::StatusOr<Lpips> other = Lpips::load_safetensors(write_weights(dir_, none, "sdxl-unet"));
  EXPECT_TRUE(contains(other.status().message(), "not an LPIPS-VGG weights file")) << other.status();

  const absl::StatusOr<Lpips> missing =
      Lpips::load_safetensors(write_weights(dir_, [](sdxl::TensorMap& t) { t.erase("lin3.model.1.weight"); }));
  EXPECT_TRUE(contains(missing.status().message(), "missing key lin3.model.1.weight")) << missing.status();

  const absl::StatusOr<Lpips> shape = Lpips::load_safetensors(write_weights(dir_, [](sdxl::TensorMap& t) {
    t["features.10.weight"] = at::zeros({256, 128, 1, 1});
  }));
  EXPECT_TRUE(contains(shape.status().message(), "features.10.weight has shape [256,128,1,1]")) << shape.status();

  const absl::StatusOr<Lpips> extra = Lpips::load_safetensors(
      write_weights(dir_, [](sdxl::TensorMap& t) { t["classifier.0.weight"] = at::zeros({1}); }));
  EXPECT_TRUE(contains(extra.status().message(), "unexpected key classifier.0.weight")) << extra.status();
}

}  // namespace
}  // namespace gaps

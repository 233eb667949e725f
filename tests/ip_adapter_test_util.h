#pragma once
// The IP-Adapter fixture (tests/fixtures/ip_adapter_tiny, made by tests/scripts/make_ip_adapter_fixtures.py
// for the UNet of tests/fixtures/sdxl_tiny), shared by sdxl_ip_adapter_test.cpp and its GPU test in gpu/.
#include <string>

#include <gtest/gtest.h>
#include "diffusion_worker/sdxl/pipeline.h"
#include "tests/sdxl_test_util.h"

namespace gaps::test {

inline std::string ip_dir() { return std::string(GAPS_TEST_SCRIPTS_DIR) + "/fixtures/ip_adapter_tiny"; }
inline std::string ip_weights() { return ip_dir() + "/ip_adapter.safetensors"; }
inline std::string image_encoder_dir() { return ip_dir() + "/image_encoder"; }

inline sdxl::TensorMap ip_reference(const std::string& name) { return fixture_reference(ip_dir(), name); }

// A pipeline with the fixture's adapter and image encoder (float32 on the CPU unless changed).
inline sdxl::PipelineOptions ip_options() {
  sdxl::PipelineOptions options;
  options.ip_adapter = ip_weights();
  options.image_encoder = image_encoder_dir();
  return options;
}

}  // namespace gaps::test

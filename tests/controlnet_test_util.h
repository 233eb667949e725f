#pragma once
// The ControlNet fixture (tests/fixtures/sdxl_controlnet_tiny, made by tests/scripts/make_controlnet_fixtures.py)
// and its recorded img2img run, shared by sdxl_controlnet_test.cpp and its GPU test in gpu/.
#include <fstream>
#include <string>

#include <gtest/gtest.h>
#include <nlohmann/json.hpp>
#include "diffusion_worker/sdxl/pipeline.h"
#include "tests/sdxl_test_util.h"

namespace gaps::test {

inline std::string controlnet_fixture_dir() {
  return std::string(GAPS_TEST_SCRIPTS_DIR) + "/fixtures/sdxl_controlnet_tiny";
}
inline std::string controlnet_dir() { return controlnet_fixture_dir() + "/controlnet"; }

inline sdxl::TensorMap controlnet_reference(const std::string& name) {
  return fixture_reference(controlnet_fixture_dir(), name);
}

// diffusers' StableDiffusionXLControlNetImg2ImgPipeline run: its settings, inputs and output.
struct ControlledRun {
  nlohmann::json setup;
  sdxl::TensorMap ref;
  sdxl::Img2ImgParams params;
};

inline ControlledRun controlled_run() {
  ControlledRun run;
  std::ifstream in(controlnet_fixture_dir() + "/reference/img2img_controlnet.json");
  run.setup = nlohmann::json::parse(in);
  run.ref = controlnet_reference("img2img_controlnet");
  run.params.strength = run.setup["strength"].get<double>();
  run.params.steps = run.setup["num_inference_steps"].get<int64_t>();
  run.params.guidance_scale = run.setup["guidance_scale"].get<double>();
  return run;
}

}  // namespace gaps::test

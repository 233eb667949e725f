// Euler discrete, DDIM, DPM-Solver++(2M) and PNDM (PLMS) against diffusers, for each timestep spacing: the schedule
// (timesteps, sigmas) and two steps from the same sample and noise predictions (the second step is
// DPM-Solver's second-order update). Tolerance: 1e-5 relative to the sample's scale (float32 scalars).
#include <memory>
#include <string>

#include <ATen/ATen.h>
#include <c10/util/Exception.h>
#include <gtest/gtest.h>
#include <nlohmann/json.hpp>

#include "common/safetensors.h"
#include "diffusion_worker/sdxl/schedulers.h"
#include "tests/sdxl_test_util.h"

namespace gaps::sdxl {
namespace {

constexpr double kTolerance = 1e-5;

nlohmann::json config_json(const std::string& class_name, const std::string& spacing) {
  return {{"_class_name", class_name},        {"beta_start", 0.00085},       {"beta_end", 0.012},
          {"beta_schedule", "scaled_linear"}, {"num_train_timesteps", 1000}, {"steps_offset", 1},
          {"timestep_spacing", spacing}};
}

struct Case {
  const char* kind;
  const char* class_name;
};

class SchedulerParityTest : public ::testing::TestWithParam<std::tuple<Case, const char*>> {};

TEST_P(SchedulerParityTest, ScheduleAndTwoStepsMatchDiffusers) {
  const auto [c, spacing] = GetParam();
  const std::string key = std::string(c.kind) + "_" + spacing;
  const TensorMap ref = test::sdxl_reference("schedulers");
  auto config = SchedulerConfig::from_json(config_json(c.class_name, spacing));
  ASSERT_TRUE(config.ok()) << config.status();
  auto scheduler = make_scheduler(*config);
  ASSERT_TRUE(scheduler.ok());
  (*scheduler)->set_timesteps(10);
  const at::Tensor timesteps = at::tensor(std::vector<float>((*scheduler)->timesteps())).to(at::kDouble);
  test::expect_close(timesteps, ref.at(key + "_timesteps"), 1e-6, key + " timesteps");
  const at::Tensor& x = ref.at("x");
  if (std::string(c.kind) == "euler") {
    test::expect_close((*scheduler)->scale_model_input(x, 0), ref.at(key + "_scaled_input"), kTolerance,
                       key + " scaled input");
  }
  const at::Tensor step1 = (*scheduler)->step(ref.at("eps"), 0, x);
  test::expect_close(step1, ref.at(key + "_step1"), kTolerance, key + " step 1");
  const at::Tensor step2 = (*scheduler)->step(ref.at("eps2"), 1, ref.at(key + "_step1"));
  test::expect_close(step2, ref.at(key + "_step2"), kTolerance, key + " step 2");
}

INSTANTIATE_TEST_SUITE_P(
    AllSpacings, SchedulerParityTest,
    ::testing::Combine(::testing::Values(Case{"euler", "EulerDiscreteScheduler"}, Case{"ddim", "DDIMScheduler"},
                                         Case{"dpmpp2m", "DPMSolverMultistepScheduler"}),
                       ::testing::Values("leading", "trailing", "linspace")),
    [](const auto& info) { return std::string(std::get<0>(info.param).kind) + "_" + std::get<1>(info.param); });

// PNDM (skip_prk_steps, SD2's scheduler) against diffusers' PNDMScheduler (tests/fixtures/pndm, made by
// tests/scripts/make_pndm_fixtures.py): the schedule of 5 steps (the second timestep repeated) and all 6
// steps chained, which pass through every branch of its linear multistep update, per spacing and
// set_alpha_to_one; and the noising at an img2img start step.
class PndmParityTest : public ::testing::TestWithParam<std::tuple<const char*, bool>> {};

TensorMap pndm_reference() {
  auto ref = read_safetensors(std::string(GAPS_TEST_SCRIPTS_DIR) + "/fixtures/pndm/pndm.safetensors");
  EXPECT_TRUE(ref.ok()) << ref.status();
  return ref.ok() ? *ref : TensorMap{};
}

std::unique_ptr<Scheduler> sd2_pndm(const std::string& spacing, bool alpha_to_one) {
  nlohmann::json j = config_json("PNDMScheduler", spacing);
  j["skip_prk_steps"] = true;
  j["set_alpha_to_one"] = alpha_to_one;
  auto config = SchedulerConfig::from_json(j);
  EXPECT_TRUE(config.ok()) << config.status();
  auto scheduler = make_scheduler(*config);
  EXPECT_TRUE(scheduler.ok()) << scheduler.status();
  return scheduler.ok() ? *std::move(scheduler) : nullptr;
}

TEST_P(PndmParityTest, ScheduleAndEveryStepMatchDiffusers) {
  const auto [spacing, alpha_to_one] = GetParam();
  const std::string key = std::string(spacing) + (alpha_to_one ? "_one" : "_first");
  const TensorMap ref = pndm_reference();
  const std::unique_ptr<Scheduler> scheduler = sd2_pndm(spacing, alpha_to_one);
  ASSERT_NE(scheduler, nullptr);
  scheduler->set_timesteps(5);
  const at::Tensor timesteps = at::tensor(std::vector<float>(scheduler->timesteps())).to(at::kDouble);
  test::expect_close(timesteps, ref.at(key + "_timesteps"), 0, key + " timesteps");
  at::Tensor sample = ref.at("x");
  for (int64_t k = 0; k < 6; ++k) {
    sample = scheduler->step(ref.at("eps" + std::to_string(k)), k, sample);
    test::expect_close(sample, ref.at(key + "_step" + std::to_string(k)), kTolerance,
                       key + " step " + std::to_string(k));
  }
}

INSTANTIATE_TEST_SUITE_P(AllSpacings, PndmParityTest,
                         ::testing::Combine(::testing::Values("leading", "trailing", "linspace"), ::testing::Bool()),
                         [](const auto& info) {
                           return std::string(std::get<0>(info.param)) + (std::get<1>(info.param) ? "_alpha_one" : "");
                         });

TEST(SchedulerTest, PndmAddNoiseAndItsOptions) {
  const TensorMap ref = pndm_reference();
  const std::unique_ptr<Scheduler> scheduler = sd2_pndm("leading", false);
  ASSERT_NE(scheduler, nullptr);
  scheduler->set_timesteps(5);
  EXPECT_FLOAT_EQ(scheduler->timesteps()[2], ref.at("noisy_timestep").item<float>());
  test::expect_close(scheduler->add_noise(ref.at("x"), ref.at("noise"), 2), ref.at("noisy"), kTolerance,
                     "noisy latents");
  const at::Tensor first = scheduler->step(ref.at("eps0"), 0, ref.at("x"));
  EXPECT_THROW(scheduler->step(ref.at("eps1"), 2, first), c10::Error) << "steps run in order";

  nlohmann::json prk = config_json("PNDMScheduler", "leading");  // diffusers' default: Runge-Kutta warm-up
  const absl::Status refused = SchedulerConfig::from_json(prk).status();
  EXPECT_EQ(refused.code(), absl::StatusCode::kUnimplemented);
  EXPECT_NE(refused.message().find("skip_prk_steps"), std::string::npos);
  prk.erase("timestep_spacing");  // PNDM's defaults: leading spacing, set_alpha_to_one false
  prk["skip_prk_steps"] = true;
  auto defaults = SchedulerConfig::from_json(prk);
  ASSERT_TRUE(defaults.ok()) << defaults.status();
  EXPECT_EQ(defaults->kind, "pndm");
  EXPECT_EQ(defaults->timestep_spacing, "leading");
  EXPECT_FALSE(defaults->set_alpha_to_one);
}

// A config without timestep_spacing takes the chosen scheduler's diffusers default: DDIM's is leading,
// Euler's and DPM-Solver's linspace.
TEST(SchedulerTest, MissingSpacingTakesTheSchedulersDiffusersDefault) {
  for (const auto& [class_name, spacing] :
       std::vector<std::pair<std::string, std::string>>{{"DDIMScheduler", "leading"},
                                                        {"EulerDiscreteScheduler", "linspace"},
                                                        {"DPMSolverMultistepScheduler", "linspace"}}) {
    nlohmann::json j = config_json(class_name, "leading");
    j.erase("timestep_spacing");
    auto config = SchedulerConfig::from_json(j);
    ASSERT_TRUE(config.ok()) << class_name << ": " << config.status();
    EXPECT_EQ(config->timestep_spacing, spacing) << class_name;
  }
  nlohmann::json euler = config_json("EulerDiscreteScheduler", "leading");
  euler.erase("timestep_spacing");
  EXPECT_EQ(SchedulerConfig::from_json(euler, "ddim")->timestep_spacing, "leading") << "the chosen scheduler's default";
}

TEST(SchedulerTest, EulerAddNoiseMatchesDiffusersAtTheStartStep) {
  const TensorMap ref = test::sdxl_reference("add_noise");
  auto scheduler = make_scheduler(*SchedulerConfig::from_json(config_json("EulerDiscreteScheduler", "leading")));
  (*scheduler)->set_timesteps(4);
  EXPECT_FLOAT_EQ((*scheduler)->timesteps()[2], ref.at("timestep").item<float>());
  test::expect_close((*scheduler)->add_noise(ref.at("x"), ref.at("noise"), 2), ref.at("noisy"), kTolerance,
                     "noisy latents");
}

TEST(SchedulerTest, UnsupportedOptionsAreErrors) {
  auto j = config_json("EulerDiscreteScheduler", "leading");
  j["use_karras_sigmas"] = true;
  EXPECT_FALSE(SchedulerConfig::from_json(j).ok());
  j = config_json("EulerDiscreteScheduler", "uniform");
  EXPECT_FALSE(SchedulerConfig::from_json(j).ok());
  j = config_json("LMSDiscreteScheduler", "leading");
  EXPECT_FALSE(SchedulerConfig::from_json(j).ok());
  j = config_json("EulerDiscreteScheduler", "leading");
  j["prediction_type"] = "v_prediction";
  EXPECT_FALSE(SchedulerConfig::from_json(j).ok());
}

TEST(SchedulerTest, ClassifierFreeGuidanceExtrapolatesFromUnconditional) {
  const at::Tensor uncond = at::full({1, 2}, 1.0), cond = at::full({1, 2}, 3.0);
  const at::Tensor guided = classifier_free_guidance(at::cat({uncond, cond}), 5.0);
  EXPECT_TRUE(at::allclose(guided, at::full({1, 2}, 11.0)));
}

}  // namespace
}  // namespace gaps::sdxl

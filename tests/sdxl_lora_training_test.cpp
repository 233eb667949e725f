// LoRA training (LoraTrainer) against torch on the tiny fixtures of tests/fixtures/lora_tiny (made by
// tests/scripts/make_lora_fixtures.py): the denoising loss and the gradient of every adapter tensor for a
// fixed x0 / noise / t / context, without and with the tiny ControlNet's residuals, and one Adam step
// (torch.optim.Adam, lr 1e-3). fp32 on the CPU; losses and gradients within 1e-4 of the largest reference
// gradient (relative), Adam's result within 1% of its step (lr); several steps equal the per-tensor update bit for
// bit. Also: a few steps on a fixed batch lower the loss, the
// seeded draws repeat, the base weights get no gradient, the adapters are frozen afterwards, and misuse
// (InferenceMode, mismatched conditioning, control images without a ControlNet) is an error.
#include <cmath>
#include <string>
#include <vector>

#include <ATen/ATen.h>
#include <ATen/core/grad_mode.h>
#include <c10/core/InferenceMode.h>
#include <gtest/gtest.h>

#include "absl/strings/str_cat.h"
#include "diffusion_worker/sdxl/controlnet.h"
#include "diffusion_worker/sdxl/lora.h"
#include "diffusion_worker/sdxl/lora_training.h"
#include "diffusion_worker/sdxl/model_folder.h"
#include "diffusion_worker/sdxl/schedulers.h"
#include "diffusion_worker/sdxl/unet.h"
#include "tests/sdxl_test_util.h"

namespace gaps {
namespace {

using sdxl::TensorMap;
using sdxl::UNetLora;
using test::contains_all;

std::string lora_fixture_dir() { return std::string(GAPS_TEST_SCRIPTS_DIR) + "/fixtures/lora_tiny"; }

TensorMap lora_reference(const std::string& name) {
  auto tensors = sdxl::read_safetensors(lora_fixture_dir() + "/reference/" + name + ".safetensors");
  EXPECT_TRUE(tensors.ok()) << tensors.status();
  return tensors.ok() ? *tensors : TensorMap{};
}

struct TinyModel {
  sdxl::UNet2DCondition unet;
  at::Tensor alphas_cumprod;
};

TinyModel tiny_model() {
  const sdxl::ModelFolder f = *sdxl::ModelFolder::open(test::sdxl_model_dir());
  auto unet = sdxl::UNet2DCondition::load(*sdxl::UNetConfig::from_json(*f.read_json("unet")), *f.read_weights("unet"),
                                          at::TensorOptions(), "unet");
  EXPECT_TRUE(unet.ok()) << unet.status();
  auto config = sdxl::SchedulerConfig::from_json(*f.read_json("scheduler", "scheduler_config.json"));
  EXPECT_TRUE(config.ok()) << config.status();
  auto scheduler = sdxl::make_scheduler(*config);
  EXPECT_TRUE(scheduler.ok()) << scheduler.status();
  return {std::move(*unet), (*scheduler)->alphas_cumprod()};
}

sdxl::LoraTrainingData training_data(const TensorMap& ref) {
  sdxl::LoraTrainingData data;
  data.latents = ref.at("x0");
  data.encoder_hidden_states = ref.at("encoder_hidden_states");
  data.text_embeds = ref.at("text_embeds");
  data.time_ids = ref.at("time_ids");
  if (ref.count("control_image")) {
    data.control_images = ref.at("control_image");
    data.conditioning_scale = ref.at("conditioning_scale").item<double>();
  }
  return data;
}

sdxl::DenoisingSample fixed_sample(const TensorMap& ref) { return {ref.at("noise"), ref.at("timesteps")}; }

// Loss and every adapter's gradient against the reference; returns the largest gradient difference.
double check_loss_and_gradients(const std::string& reference, const sdxl::ControlNet* controlnet) {
  TinyModel model = tiny_model();
  auto lora = UNetLora::load(lora_fixture_dir() + "/pytorch_lora_weights.safetensors", model.unet);
  EXPECT_TRUE(lora.ok()) << lora.status();
  const TensorMap ref = lora_reference(reference);
  sdxl::LoraTrainer trainer(model.unet, *lora, model.alphas_cumprod, controlnet, {});
  auto loss = trainer.loss(training_data(ref), fixed_sample(ref));
  EXPECT_TRUE(loss.ok()) << loss.status();
  EXPECT_NEAR(loss->item<double>(), ref.at("loss").item<double>(), 1e-5 * ref.at("loss").item<double>());
  loss->backward();
  double scale = 0, diff = 0;
  for (const auto& a : lora->adapters()) {
    for (const auto& [suffix, tensor] :
         {std::pair<std::string, at::Tensor>{".lora_A.weight", a.down}, {".lora_B.weight", a.up}}) {
      const at::Tensor expected = ref.at("grad." + a.module + suffix);
      EXPECT_TRUE(tensor.grad().defined()) << a.module << suffix;
      scale = std::max(scale, expected.abs().max().item<double>());
      diff = std::max(diff, (tensor.grad() - expected).abs().max().item<double>());
    }
  }
  EXPECT_GT(scale, 1e-3);
  EXPECT_LE(diff, 1e-4 * scale) << "largest gradient " << scale;
  return diff;
}

TEST(LoraTrainingTest, LossAndGradientsMatchTorch) {
  const double diff = check_loss_and_gradients("train_step", nullptr);
  RecordProperty("max_gradient_abs_diff", absl::StrCat(diff));
}

TEST(LoraTrainingTest, LossAndGradientsWithControlNetResidualsMatchTorch) {
  auto controlnet =
      sdxl::ControlNet::load_folder(std::string(GAPS_TEST_SCRIPTS_DIR) + "/fixtures/sdxl_controlnet_tiny/controlnet",
                                    at::TensorOptions().dtype(at::kFloat));
  ASSERT_TRUE(controlnet.ok()) << controlnet.status();
  const double diff = check_loss_and_gradients("train_step_controlled", &*controlnet);
  RecordProperty("max_gradient_abs_diff", absl::StrCat(diff));
}

TEST(LoraTrainingTest, AdamStepMatchesTorchAndLeavesTheBaseWeightsAlone) {
  TinyModel model = tiny_model();
  auto lora = UNetLora::load(lora_fixture_dir() + "/pytorch_lora_weights.safetensors", model.unet);
  ASSERT_TRUE(lora.ok()) << lora.status();
  const TensorMap ref = lora_reference("train_step");
  sdxl::LoraTrainingOptions options;
  options.learning_rate = 1e-3;
  {
    sdxl::LoraTrainer trainer(model.unet, *lora, model.alphas_cumprod, nullptr, options);
    auto loss = trainer.step(training_data(ref), fixed_sample(ref));
    ASSERT_TRUE(loss.ok()) << loss.status();
    EXPECT_NEAR(*loss, ref.at("loss").item<double>(), 1e-5 * ref.at("loss").item<double>());
  }
  double diff = 0;
  for (const auto& a : lora->adapters()) {
    diff = std::max(diff, (a.down - ref.at("after." + a.module + ".lora_A.weight")).abs().max().item<double>());
    diff = std::max(diff, (a.up - ref.at("after." + a.module + ".lora_B.weight")).abs().max().item<double>());
    EXPECT_FALSE(a.down.requires_grad()) << a.module;  // frozen once the trainer is gone
  }
  // A first Adam step moves each entry by about lr * sign(g); entries whose gradient is within a few eps of
  // zero move by less and carry the gradients' float32 differences, hence 1% of lr rather than float epsilon.
  EXPECT_LE(diff, 1e-5);
  RecordProperty("max_adam_abs_diff", absl::StrCat(diff));
  model.unet.for_each_attention([](const std::string& name, sdxl::Attention& attn) {
    EXPECT_FALSE(attn.to_q.weight.requires_grad()) << name;
    EXPECT_FALSE(attn.to_out.weight.grad().defined()) << name;
  });
}

// torch.optim.Adam's update of one tensor, written out: the readable reference of the trainer's
// multi-tensor update.
void reference_adam(at::Tensor& p, at::Tensor& m, at::Tensor& v, const at::Tensor& g, int64_t step,
                    const sdxl::LoraTrainingOptions& o) {
  m.mul_(o.beta1).add_(g, 1 - o.beta1);
  v.mul_(o.beta2).addcmul_(g, g, 1 - o.beta2);
  const double correction1 = 1 - std::pow(o.beta1, step), correction2 = 1 - std::pow(o.beta2, step);
  const at::Tensor denominator = (v.sqrt() / std::sqrt(correction2)).add_(o.epsilon);
  p.addcdiv_(m, denominator, -o.learning_rate / correction1);
}

// Several steps of the trainer equal, bit for bit, the same gradients followed by the per-tensor update above
// (bias corrections of later steps included).
TEST(LoraTrainingTest, AdamStepsEqualThePerTensorUpdate) {
  const TensorMap ref = lora_reference("train_step");
  sdxl::LoraTrainingOptions options;
  options.learning_rate = 1e-2;
  TinyModel trained_model = tiny_model(), reference_model = tiny_model();
  auto trained = UNetLora::load(lora_fixture_dir() + "/pytorch_lora_weights.safetensors", trained_model.unet);
  auto reference = UNetLora::load(lora_fixture_dir() + "/pytorch_lora_weights.safetensors", reference_model.unet);
  ASSERT_TRUE(trained.ok() && reference.ok());
  sdxl::LoraTrainer trainer(trained_model.unet, *trained, trained_model.alphas_cumprod, nullptr, options);
  // The reference's gradients come from a trainer of its own, whose update is not used.
  const sdxl::LoraTrainer gradients(reference_model.unet, *reference, reference_model.alphas_cumprod, nullptr, options);
  std::vector<at::Tensor> parameters = reference->parameters(), first, second;
  for (const at::Tensor& p : parameters) {
    first.push_back(at::zeros_like(p));
    second.push_back(at::zeros_like(p));
  }
  for (int64_t step = 1; step <= 3; ++step) {
    ASSERT_TRUE(trainer.step(training_data(ref), fixed_sample(ref)).ok());
    for (at::Tensor& p : parameters) p.mutable_grad() = at::Tensor();
    auto loss = gradients.loss(training_data(ref), fixed_sample(ref));
    ASSERT_TRUE(loss.ok()) << loss.status();
    loss->backward();
    at::NoGradGuard no_grad;
    for (size_t i = 0; i < parameters.size(); ++i)
      reference_adam(parameters[i], first[i], second[i], parameters[i].grad(), step, options);
  }
  const std::vector<at::Tensor> after = trained->parameters();
  ASSERT_EQ(after.size(), parameters.size());
  for (size_t i = 0; i < after.size(); ++i) EXPECT_TRUE(at::equal(after[i], parameters[i])) << "tensor " << i;
}

TEST(LoraTrainingTest, StepsOnAFixedBatchLowerTheLoss) {
  TinyModel model = tiny_model();
  auto lora = UNetLora::create(model.unet, {}, 3);
  ASSERT_TRUE(lora.ok()) << lora.status();
  const TensorMap ref = lora_reference("train_step");
  sdxl::LoraTrainingOptions options;
  options.learning_rate = 1e-2;
  sdxl::LoraTrainer trainer(model.unet, *lora, model.alphas_cumprod, nullptr, options);
  std::vector<double> losses;
  for (int i = 0; i < 6; ++i) {
    auto loss = trainer.step(training_data(ref), fixed_sample(ref));
    ASSERT_TRUE(loss.ok()) << loss.status();
    losses.push_back(*loss);
  }
  EXPECT_LT(losses.back(), 0.97 * losses.front()) << losses.front() << " -> " << losses.back();
}

TEST(LoraTrainingTest, SeededTrainingRepeats) {
  const TensorMap ref = lora_reference("train_step");
  sdxl::LoraTrainingOptions options;
  options.steps = 3;
  options.learning_rate = 1e-3;
  options.seed = 5;
  std::vector<std::vector<double>> runs;
  std::vector<at::Tensor> first_up;
  for (int run = 0; run < 2; ++run) {
    TinyModel model = tiny_model();
    auto lora = UNetLora::create(model.unet, {}, 3);
    ASSERT_TRUE(lora.ok()) << lora.status();
    sdxl::LoraTrainer trainer(model.unet, *lora, model.alphas_cumprod, nullptr, options);
    auto losses = trainer.train(training_data(ref));
    ASSERT_TRUE(losses.ok()) << losses.status();
    ASSERT_EQ(losses->size(), 3u);
    runs.push_back(*losses);
    first_up.push_back(lora->adapters().front().up.clone());
  }
  EXPECT_EQ(runs[0], runs[1]);
  EXPECT_TRUE(at::equal(first_up[0], first_up[1]));
  EXPECT_GT(first_up[0].abs().max().item<double>(), 0.0);  // trained away from B = 0
}

TEST(LoraTrainingTest, MisuseIsAnError) {
  TinyModel model = tiny_model();
  auto lora = UNetLora::create(model.unet, {}, 3);
  ASSERT_TRUE(lora.ok()) << lora.status();
  const TensorMap ref = lora_reference("train_step");
  sdxl::LoraTrainer trainer(model.unet, *lora, model.alphas_cumprod, nullptr, {});
  {
    c10::InferenceMode inference;
    auto loss = trainer.step(training_data(ref), fixed_sample(ref));
    ASSERT_FALSE(loss.ok());
    EXPECT_TRUE(contains_all(std::string(loss.status().message()), {"InferenceMode"}));
  }
  sdxl::LoraTrainingData data = training_data(ref);
  data.text_embeds = data.text_embeds.narrow(0, 0, 1);
  EXPECT_TRUE(contains_all(std::string(trainer.train(data).status().message()), {"text_embeds", "one entry per view"}));
  data = training_data(ref);
  data.control_images = at::zeros({2, 3, 16, 12});
  EXPECT_TRUE(contains_all(std::string(trainer.train(data).status().message()), {"no ControlNet"}));
  auto wrong_noise = trainer.loss(training_data(ref), {at::zeros({1, 4, 8, 6}), ref.at("timesteps")});
  EXPECT_TRUE(contains_all(std::string(wrong_noise.status().message()), {"noise", "[1, 4, 8, 6]"}));
}

// A CUDA graph of the step is asked for views on the CPU: an error that says so, nothing trained.
TEST(LoraTrainingTest, ACudaGraphOfViewsOnTheCpuIsAnError) {
  TinyModel model = tiny_model();
  auto lora = UNetLora::create(model.unet, {}, 3);
  ASSERT_TRUE(lora.ok()) << lora.status();
  const at::Tensor up_before = lora->adapters()[0].up.clone();
  sdxl::LoraTrainingOptions options;
  options.steps = 3;
  options.cuda_graph = true;
  sdxl::LoraTrainer trainer(model.unet, *lora, model.alphas_cumprod, nullptr, options);
  const auto losses = trainer.train(training_data(lora_reference("train_step")));
  ASSERT_FALSE(losses.ok());
  EXPECT_TRUE(contains_all(std::string(losses.status().message()), {"CUDA"})) << losses.status();
  EXPECT_TRUE(at::equal(lora->adapters()[0].up, up_before));
}

}  // namespace
}  // namespace gaps

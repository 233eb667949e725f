// The deployment users run on a GPU: gaps-worker and gaps-trainer started as processes with --device cuda,
// a job of the method submitted through the client, at least one pseudo-view generated and admitted, and the
// finished model rendered on the GPU through RenderView (as `gaps render --job` does).
// A vanilla job on fern initialised by PatchMatch on the trainer's GPU with settings of its own (InitSettings).
#include <filesystem>
#include <memory>
#include <string>
#include <vector>

#include <absl/strings/str_join.h>
#include <gtest/gtest.h>
#include <nlohmann/json.hpp>

#include "client/remote_client.h"
#include "common/image_io.h"
#include "rpc/config_codec.h"
#include "tests/gpu/require_cuda.h"
#include "tests/process_util.h"
#include "tests/restore_test_util.h"
#include "tests/synthetic_scene_util.h"
#include "tests/test_util.h"

namespace gaps {
namespace {

using test::Process;

struct FinishedJob {
  std::string id;
  v1::JobStatus status;
  int phases = 0, skipped = 0, admitted = 0;
};

struct ServicesOnCuda : test::TempDirTest {
  // Starts the worker with `worker_flags` and a trainer on cuda with `trainer_flags`, and connects the client.
  void start_services(const std::vector<std::string>& worker_flags, const std::vector<std::string>& trainer_flags) {
    start_services(std::vector<std::vector<std::string>>{worker_flags}, trainer_flags);
  }
  // The same with one worker per entry of `workers_flags`, all in the trainer's pool.
  void start_services(const std::vector<std::vector<std::string>>& workers_flags,
                      const std::vector<std::string>& trainer_flags) {
    std::vector<std::string> addresses;
    for (size_t k = 0; k < workers_flags.size(); ++k) {
      std::vector<std::string> worker_args = {GAPS_WORKER_BIN, "--listen", "127.0.0.1:0"};
      worker_args.insert(worker_args.end(), workers_flags[k].begin(), workers_flags[k].end());
      workers_.push_back(std::make_unique<Process>(worker_args, dir_ / ("worker" + std::to_string(k) + ".log")));
      const int worker_port = workers_.back()->wait_for_port();
      ASSERT_GT(worker_port, 0) << workers_.back()->log_text();
      addresses.push_back("127.0.0.1:" + std::to_string(worker_port));
    }
    worker_ = workers_.front().get();
    std::vector<std::string> trainer_args = {GAPS_TRAINER_BIN,
                                             "--listen",
                                             "127.0.0.1:0",
                                             "--data_dir",
                                             (dir_ / "data").string(),
                                             "--device",
                                             "cuda",
                                             "--workers",
                                             absl::StrJoin(addresses, ",")};
    trainer_args.insert(trainer_args.end(), trainer_flags.begin(), trainer_flags.end());
    trainer_ = std::make_unique<Process>(trainer_args, dir_ / "trainer.log");
    const int trainer_port = trainer_->wait_for_port();
    ASSERT_GT(trainer_port, 0) << trainer_->log_text();
    auto client = client::TrainerClient::connect("127.0.0.1:" + std::to_string(trainer_port), {});
    ASSERT_TRUE(client.ok()) << client.status();
    client_ = std::make_unique<client::TrainerClient>(std::move(*client));
  }

  // Submits `spec` with `scene`, follows it to its end counting its phases, and fetches its files into fetched/.
  void run_job(const v1::JobSpec& spec, const client::PreparedScene& scene, FinishedJob* finished) {
    auto job = client_->submit(spec, scene);
    ASSERT_TRUE(job.ok()) << job.status();
    finished->id = *job;
    auto status = client_->watch(*job, [&](const v1::JobEvent& e) {
      if (!e.has_phase_finished()) return;
      ++finished->phases;
      finished->skipped += e.phase_finished().skipped();
      finished->admitted += e.phase_finished().admitted();
    });
    ASSERT_TRUE(status.ok()) << status.status() << "\n" << trainer_->log_text();
    finished->status = *status;
    auto files = client_->fetch(*job, dir_ / "fetched");
    ASSERT_TRUE(files.ok()) << files.status();
  }

  // run_job for a job whose points PatchMatch makes on the trainer's GPU: it succeeds on CUDA from "mvs"; *metrics:
  // its metrics.json.
  void run_mvs_job(const v1::JobSpec& spec, const client::PreparedScene& scene, nlohmann::json* metrics) {
    FinishedJob job;
    ASSERT_NO_FATAL_FAILURE(run_job(spec, scene, &job));
    EXPECT_EQ(job.status.state(), v1::SUCCEEDED) << job.status.error() << "\n" << trainer_->log_text();
    *metrics = test::read_json(dir_ / "fetched" / "metrics.json");
    EXPECT_EQ((*metrics)["device"].get<std::string>().rfind("cuda", 0), 0u) << (*metrics)["device"];
    EXPECT_EQ((*metrics)["init_method"], "mvs") << trainer_->log_text();
  }

  // A job of the method on a small synthetic scene, through services started as start_services does.
  void run_full_job(const std::vector<std::string>& worker_flags, const std::vector<std::string>& trainer_flags,
                    const nlohmann::json& gaps_fields, FinishedJob* finished) {
    run_full_job(std::vector<std::vector<std::string>>{worker_flags}, trainer_flags, gaps_fields, finished);
  }
  void run_full_job(const std::vector<std::vector<std::string>>& workers_flags,
                    const std::vector<std::string>& trainer_flags, const nlohmann::json& gaps_fields,
                    FinishedJob* finished) {
    ASSERT_NO_FATAL_FAILURE(start_services(workers_flags, trainer_flags));
    auto scene = test::prepared_synthetic_scene(dir_ / "scene", 96, 72);
    ASSERT_TRUE(scene.ok()) << scene.status();
    v1::JobSpec spec;
    spec.set_name("cuda");
    spec.mutable_config()->set_views(3);
    spec.mutable_config()->set_init("random");
    spec.mutable_config()->set_random_points(3000);
    spec.mutable_config()->set_variant("full");
    ASSERT_TRUE(
        rpc::set_fields({{"iterations", 300}, {"device", "cuda"}}, spec.mutable_config()->mutable_training()).ok());
    nlohmann::json fields = {{"warmup_iterations", 100}, {"phase_interval", 100}, {"n_active", 4}};
    fields.update(gaps_fields);
    ASSERT_TRUE(rpc::set_fields(fields, spec.mutable_config()->mutable_gaps()).ok());
    ASSERT_NO_FATAL_FAILURE(run_job(spec, *scene, finished));
  }

  // A full job with an sdxl worker on the tiny models (every constraint, inpainting in every phase) sharing a
  // capped card with the trainer; extra_options join the worker's backend options.
  void run_sdxl_job(const nlohmann::json& extra_options);

  std::vector<std::unique_ptr<Process>> workers_;
  Process* worker_ = nullptr;  // the first of workers_
  std::unique_ptr<Process> trainer_;
  std::unique_ptr<client::TrainerClient> client_;
};

// The admission gate's structure criterion (0.4) is calibrated on real scenes; the short jobs here judge views
// of a 96x72 synthetic scene after 100 iterations from random points, whose proposals measure SSIM 0.2-0.43 (a
// CPU run of the same job admitted 4 of 8), so these service tests, which are about the path, admit from 0.2.
const nlohmann::json kShortJobGate = {{"admit_min_structure", 0.2}};

TEST_F(ServicesOnCuda, AFullJobWithAWorkerAndATrainerOnCudaAdmitsPseudoViews) {
  GAPS_REQUIRE_CUDA();
  FinishedJob job;
  ASSERT_NO_FATAL_FAILURE(run_full_job({"--backend", "reproject", "--device", "cuda"}, {}, kShortJobGate, &job));
  EXPECT_EQ(job.status.state(), v1::SUCCEEDED) << job.status.error() << "\n" << trainer_->log_text();
  EXPECT_EQ(job.phases, 2);
  EXPECT_EQ(job.skipped, 0) << worker_->log_text();
  EXPECT_GE(job.admitted, 1);
  const nlohmann::json metrics = test::read_json(dir_ / "fetched" / "metrics.json");
  EXPECT_EQ(metrics["device"].get<std::string>().rfind("cuda", 0), 0u) << metrics["device"];
  EXPECT_EQ(metrics["peak_memory"]["kind"], "cuda_allocator");
  // On one host the payloads (compact: bytes for colour and alpha) went through shared memory.
  const nlohmann::json phases = test::read_json(dir_ / "fetched" / "phases.json");
  ASSERT_EQ(phases.size(), 2u);
  for (const nlohmann::json& phase : phases) {
    EXPECT_EQ(phase["generator_counters"]["shared_memory"], 1.0) << phase["generator_counters"];
    EXPECT_GT(phase["generator_counters"]["shared_memory_bytes"].get<double>(), 0.0);
    EXPECT_TRUE(phase["generator_stages"].contains("client_encode")) << phase["generator_stages"];
  }

  // RenderView on the trainer's GPU gives the job's own test renders (renders/, also made on the GPU), frame
  // after frame from the model the service keeps.
  auto cameras = client_->job_cameras(job.id);
  ASSERT_TRUE(cameras.ok()) << cameras.status();
  ASSERT_GT(cameras->test_size(), 0);
  for (int repeat = 0; repeat < 2; ++repeat) {
    for (const v1::Camera& camera : cameras->test()) {
      auto rendered = client_->render(job.id, camera);
      ASSERT_TRUE(rendered.ok()) << rendered.status();
      auto saved = read_image(dir_ / "fetched" / "renders" / camera.name());
      ASSERT_TRUE(saved.ok()) << saved.status();
      EXPECT_LE((*rendered - *saved).abs().max().item<float>(), 1.0f / 255 + 1e-6) << camera.name();
      EXPECT_GT(rendered->std().item<float>(), 0.01f) << camera.name();
    }
  }
}

// Two workers, on two GPUs where the machine has them: each phase's poses are shared between them (the trainer's
// default, --worker_fan_out), with asynchronous phases as a two-GPU deployment runs them.
TEST_F(ServicesOnCuda, AFullJobSharesEachPhaseBetweenTwoWorkers) {
  GAPS_REQUIRE_CUDA();
  const std::string second = at::getNumGPUs() > 1 ? "cuda:1" : "cuda:0";
  FinishedJob job;
  nlohmann::json fields = kShortJobGate;
  fields["async_iterations"] = 50;
  ASSERT_NO_FATAL_FAILURE(
      run_full_job({{"--backend", "reproject", "--device", "cuda:0"}, {"--backend", "reproject", "--device", second}},
                   {}, fields, &job));
  EXPECT_EQ(job.status.state(), v1::SUCCEEDED) << job.status.error() << "\n" << trainer_->log_text();
  EXPECT_EQ(job.phases, 2);
  EXPECT_EQ(job.skipped, 0) << workers_[0]->log_text() << workers_[1]->log_text();
  EXPECT_GE(job.admitted, 1);
  for (const nlohmann::json& phase : test::read_json(dir_ / "fetched" / "phases.json")) {
    EXPECT_EQ(phase["generator_counters"]["workers"], 2.0) << phase["generator_counters"];
    EXPECT_TRUE(phase.contains("async")) << phase.dump();
  }
}

// The hand-over the trainer's flags choose: float32 payloads in the messages, as before shared memory and compact
// encoding existed.
TEST_F(ServicesOnCuda, AFullJobWithFloat32PayloadsInTheMessagesRunsToo) {
  GAPS_REQUIRE_CUDA();
  FinishedJob job;
  ASSERT_NO_FATAL_FAILURE(run_full_job({"--backend", "reproject", "--device", "cuda"},
                                       {"--worker_encoding", "float32", "--noworker_shared_memory"}, kShortJobGate,
                                       &job));
  EXPECT_EQ(job.status.state(), v1::SUCCEEDED) << job.status.error() << "\n" << trainer_->log_text();
  EXPECT_EQ(job.skipped, 0) << worker_->log_text();
  EXPECT_GE(job.admitted, 1);
  for (const nlohmann::json& phase : test::read_json(dir_ / "fetched" / "phases.json")) {
    EXPECT_EQ(phase["generator_counters"]["shared_memory"], 0.0) << phase["generator_counters"];
    // 16 float32 bytes per pixel at least (colour and depth) of 96x72 poses.
    EXPECT_GT(phase["generator_counters"]["request_bytes"].get<double>(), 4 * 96 * 72 * 16.0);
  }
}

// The restore backend (Real-ESRGAN x4plus, float16 on the worker's GPU, composed with reproject's warp) serving a
// job of the method through the services.
TEST_F(ServicesOnCuda, ARestoreWorkerOnCudaServesAFullJob) {
  GAPS_REQUIRE_CUDA();
  if (auto reason = test::real_weights_skip_reason()) GTEST_SKIP() << *reason;
  FinishedJob job;
  ASSERT_NO_FATAL_FAILURE(
      run_full_job({"--backend", "restore", "--device", "cuda", "--backend-options", R"({"compose": "reproject"})"}, {},
                   kShortJobGate, &job));
  EXPECT_EQ(job.status.state(), v1::SUCCEEDED) << job.status.error() << "\n" << trainer_->log_text();
  EXPECT_EQ(job.phases, 2);
  EXPECT_EQ(job.skipped, 0) << worker_->log_text();
  EXPECT_GE(job.admitted, 1);
  const nlohmann::json metrics = test::read_json(dir_ / "fetched" / "metrics.json");
  EXPECT_TRUE(test::contains(metrics["generator"].get<std::string>(), "restore 1 compose:reproject"))
      << metrics["generator"];
}

// The sdxl backend as users run it on a card shared with the trainer: both processes with --gpu-memory-gib
// caps, the worker in fp16 with every component of the method (ControlNet depth, IP-Adapter, LoRA scene
// adaptation, SD2 inpainting, Depth-Anything) on the tiny random models; the phases record where their time
// went, the LoRA training (AdaptScene) and img2img among it.
// The sdxl backend's options with every component on the tiny random models, in fp16.
nlohmann::json tiny_sdxl_options() {
  const std::string fixtures = std::string(GAPS_TEST_SCRIPTS_DIR) + "/fixtures/";
  return {
      {"weights", fixtures + "sdxl_tiny/model"},
      {"dtype", "float16"},
      {"steps", 4},
      {"controlnet", fixtures + "sdxl_controlnet_tiny/controlnet"},
      {"ip_adapter", fixtures + "ip_adapter_tiny/ip_adapter.safetensors"},
      {"image_encoder", fixtures + "ip_adapter_tiny/image_encoder"},
      {"inpaint", fixtures + "sd2_inpaint_tiny/model"},
      {"inpaint_steps", 2},
      {"depth_anything", fixtures + "depth_anything_tiny/model"},
  };
}

void ServicesOnCuda::run_sdxl_job(const nlohmann::json& extra_options) {
  nlohmann::json options = tiny_sdxl_options();
  options.update(extra_options);
  FinishedJob job;
  ASSERT_NO_FATAL_FAILURE(run_full_job(
      {"--backend", "sdxl", "--device", "cuda", "--gpu-memory-gib", "3", "--backend-options", options.dump()},
      {"--gpu-memory-gib", "2"},
      // Every view inpainted: the second stage runs in each phase.
      {{"lora_steps", 3}, {"inpaint_uncovered_fraction", 0.0}}, &job));
  EXPECT_EQ(job.status.state(), v1::SUCCEEDED) << job.status.error() << "\n" << trainer_->log_text();
  EXPECT_EQ(job.phases, 2);
  EXPECT_EQ(job.skipped, 0) << worker_->log_text();
  const nlohmann::json phases = test::read_json(dir_ / "fetched" / "phases.json");
  ASSERT_EQ(phases.size(), 2u);
  for (size_t k = 0; k < phases.size(); ++k) {
    const nlohmann::json& stages = phases[k]["generator_stages"];
    for (const char* stage : {"img2img", "inpaint", "worker_generate", "transfer"})
      EXPECT_TRUE(stages.contains(stage)) << k << " " << stage << " " << stages;
    EXPECT_EQ(stages.contains("adapt_scene"), k == 0) << stages;
    EXPECT_GT(phases[k]["seconds"]["generation"].get<double>(), 0.0);
  }
  EXPECT_EQ(test::read_json(dir_ / "fetched" / "metrics.json")["peak_memory"]["kind"], "cuda_allocator");
}

TEST_F(ServicesOnCuda, AnSdxlWorkerAndATrainerSharingOneCappedCardRunAFullJob) {
  GAPS_REQUIRE_CUDA();
  run_sdxl_job(nlohmann::json::object());
}

// The worker as the deployment would run it faster: convolutions channels-last, the UNet replayed from graphs.
TEST_F(ServicesOnCuda, AnSdxlWorkerWithChannelsLastConvolutionsAndGraphsRunsAFullJob) {
  GAPS_REQUIRE_CUDA();
  run_sdxl_job({{"channels_last", true}, {"cuda_graphs", true}});
}

// Two sdxl workers (on two GPUs where the machine has them) share one scene adaptation: the first trains the LoRA,
// the trainer hands its adapters to the second, which installs them (--worker-share-adaptation, the default).
TEST_F(ServicesOnCuda, TwoSdxlWorkersShareOneLoraAdaptation) {
  GAPS_REQUIRE_CUDA();
  const std::string second = at::getNumGPUs() > 1 ? "cuda:1" : "cuda:0";
  nlohmann::json options = tiny_sdxl_options();
  options["channels_last"] = true;
  options["cuda_graphs"] = true;
  const std::vector<std::string> flags = {"--backend", "sdxl", "--backend-options", options.dump()};
  std::vector<std::string> first_flags = flags, second_flags = flags;
  for (auto [worker, device] : {std::pair{&first_flags, "cuda:0"}, std::pair{&second_flags, second.c_str()}}) {
    worker->push_back("--device");
    worker->push_back(device);
  }
  FinishedJob job;
  ASSERT_NO_FATAL_FAILURE(
      run_full_job({first_flags, second_flags}, {}, {{"lora_steps", 3}, {"async_iterations", 50}}, &job));
  EXPECT_EQ(job.status.state(), v1::SUCCEEDED) << job.status.error() << "\n" << trainer_->log_text();
  EXPECT_EQ(job.phases, 2);
  EXPECT_EQ(job.skipped, 0) << workers_[0]->log_text() << workers_[1]->log_text();
  const nlohmann::json phases = test::read_json(dir_ / "fetched" / "phases.json");
  ASSERT_EQ(phases.size(), 2u);
  const nlohmann::json& first = phases[0]["generator_counters"];
  EXPECT_EQ(first["adaptations_made"], 1.0) << first;
  EXPECT_EQ(first["adaptations_installed"], 1.0) << first;
  EXPECT_GT(first["adaptation_export_bytes"].get<double>(), 0.0) << first;
  EXPECT_EQ(phases[1]["generator_counters"]["workers"], 2.0) << phases[1]["generator_counters"];
}

// A job whose initialisation runs PatchMatch on the trainer's GPU from fern's 3 training views with PatchMatch and
// fusion settings of its own (InitSettings, what gaps submit --patchmatch-... sends).
TEST_F(ServicesOnCuda, AJobWithInitSettingsRunsPatchMatchOnTheTrainersGpu) {
  GAPS_REQUIRE_CUDA();
  const std::filesystem::path fern = GAPS_DATA_DIR "/llff/fern";
  if (!std::filesystem::exists(fern)) GTEST_SKIP() << "no LLFF fern under " << fern;
  ASSERT_NO_FATAL_FAILURE(start_services({"--backend", "reproject", "--device", "cuda"}, {}));
  auto scene = client::prepare_scene(fern, 8);
  ASSERT_TRUE(scene.ok()) << scene.status();
  v1::JobSpec spec;
  spec.set_name("fern-mvs");
  spec.mutable_config()->set_views(3);
  spec.mutable_config()->set_init("mvs");
  spec.mutable_config()->set_variant("vanilla");
  ASSERT_TRUE(
      rpc::set_fields({{"iterations", 200}, {"device", "cuda"}}, spec.mutable_config()->mutable_training()).ok());
  ASSERT_TRUE(
      rpc::set_fields({{"patchmatch_iterations", 3}, {"fusion_max_normal_error", 30.0}, {"sparse_max_image_side", 400}},
                      spec.mutable_config()->mutable_init_settings())
          .ok());
  nlohmann::json metrics;
  ASSERT_NO_FATAL_FAILURE(run_mvs_job(spec, *scene, &metrics));
  EXPECT_EQ(metrics["init_options"]["patchmatch_iterations"], 3) << metrics["init_options"];
  EXPECT_EQ(metrics["init_options"]["fusion_max_normal_error"], 30.0) << metrics["init_options"];
  EXPECT_EQ(metrics["init_options"]["patchmatch_best_views"], 1) << metrics["init_options"];  // a default
  EXPECT_EQ(metrics["init_options"]["sparse_max_image_side"], 400) << metrics["init_options"];
}

// A job left at init "auto" on fern (forward-facing): gaps submit uploads the 3 training views at twice their size
// (1008x756) and the trainer runs PatchMatch on them on its GPU, as `gaps train` would.
TEST_F(ServicesOnCuda, AnAutoJobRunsPatchMatchOnTheUploadedLargerViewsOnTheTrainersGpu) {
  GAPS_REQUIRE_CUDA();
  const std::filesystem::path fern = GAPS_DATA_DIR "/llff/fern";
  if (!std::filesystem::exists(fern)) GTEST_SKIP() << "no LLFF fern under " << fern;
  // The larger views come from images_4, which a copy of the data may leave out (it is not needed at -r 8).
  if (!std::filesystem::exists(fern / "images_4")) GTEST_SKIP() << "fern's images_4 not found under " << fern;
  ASSERT_NO_FATAL_FAILURE(start_services({"--backend", "reproject", "--device", "cuda"}, {}));
  RunOptions o;
  o.scene_dir = fern;
  o.views = 3;
  o.resolution = 8;
  auto scene = client::prepare_scene(fern, o.resolution);
  ASSERT_TRUE(scene.ok()) << scene.status();
  ASSERT_TRUE(client::add_larger_training_views(o, &*scene).ok());
  ASSERT_EQ(scene->larger_images.size(), 3u);
  v1::JobSpec spec;
  spec.set_name("fern-auto");
  spec.mutable_config()->set_views(3);
  spec.mutable_config()->set_variant("vanilla");
  ASSERT_TRUE(
      rpc::set_fields({{"iterations", 200}, {"device", "cuda"}}, spec.mutable_config()->mutable_training()).ok());
  nlohmann::json metrics;
  ASSERT_NO_FATAL_FAILURE(run_mvs_job(spec, *scene, &metrics));
  EXPECT_EQ(metrics["init_resolution"], 0.5) << metrics;
  EXPECT_EQ(metrics["init_options"]["patchmatch_max_image_side"], 1008) << metrics["init_options"];
  EXPECT_EQ(metrics["init_options"]["sparse_max_image_side"], 504) << metrics["init_options"];
}

}  // namespace
}  // namespace gaps

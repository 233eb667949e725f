// The deployment users run on a GPU: gaps-worker and gaps-trainer started as processes with --device cuda,
// a job of the method submitted through the client, at least one pseudo-view generated and admitted, and the
// finished model rendered on the GPU through RenderView (as `gaps render --job` does).
#include <fstream>
#include <string>

#include <gtest/gtest.h>
#include <nlohmann/json.hpp>

#include "client/remote_client.h"
#include "common/image_io.h"
#include "gs_trainer/synthetic.h"
#include "rpc/config_codec.h"
#include "tests/gpu/require_cuda.h"
#include "tests/process_util.h"
#include "tests/test_util.h"

namespace gaps {
namespace {

using test::Process;

struct ServicesOnCuda : test::TempDirTest {};

TEST_F(ServicesOnCuda, AFullJobWithAWorkerAndATrainerOnCudaAdmitsPseudoViews) {
  GAPS_REQUIRE_CUDA();
  Process worker({GAPS_WORKER_BIN, "--listen", "127.0.0.1:0", "--backend", "reproject", "--device", "cuda"},
                 dir_ / "worker.log");
  const int worker_port = worker.wait_for_port();
  ASSERT_GT(worker_port, 0) << worker.log_text();
  Process trainer({GAPS_TRAINER_BIN, "--listen", "127.0.0.1:0", "--data_dir", (dir_ / "data").string(), "--device",
                   "cuda", "--workers", "127.0.0.1:" + std::to_string(worker_port)},
                  dir_ / "trainer.log");
  const int trainer_port = trainer.wait_for_port();
  ASSERT_GT(trainer_port, 0) << trainer.log_text();

  SyntheticSceneOptions scene_options;
  scene_options.images = 9;
  scene_options.width = 96;
  scene_options.height = 72;
  ASSERT_TRUE(write_synthetic_scene(dir_ / "scene", scene_options).ok());
  auto scene = client::prepare_scene(dir_ / "scene", 1);
  ASSERT_TRUE(scene.ok()) << scene.status();
  v1::JobSpec spec;
  spec.set_name("cuda");
  spec.mutable_config()->set_views(3);
  spec.mutable_config()->set_init("random");
  spec.mutable_config()->set_random_points(3000);
  spec.mutable_config()->set_variant("full");
  ASSERT_TRUE(
      rpc::set_fields({{"iterations", 300}, {"device", "cuda"}}, spec.mutable_config()->mutable_training()).ok());
  ASSERT_TRUE(rpc::set_fields({{"warmup_iterations", 100}, {"phase_interval", 100}, {"n_active", 4}},
                              spec.mutable_config()->mutable_gaps())
                  .ok());
  auto client = client::TrainerClient::connect("127.0.0.1:" + std::to_string(trainer_port), {});
  ASSERT_TRUE(client.ok()) << client.status();
  auto job = client->submit(spec, *scene);
  ASSERT_TRUE(job.ok()) << job.status();
  int phases = 0, skipped = 0, admitted = 0;
  auto status = client->watch(*job, [&](const v1::JobEvent& e) {
    if (!e.has_phase_finished()) return;
    ++phases;
    skipped += e.phase_finished().skipped();
    admitted += e.phase_finished().admitted();
  });
  ASSERT_TRUE(status.ok()) << status.status() << "\n" << trainer.log_text();
  EXPECT_EQ(status->state(), v1::SUCCEEDED) << status->error() << "\n" << trainer.log_text();
  EXPECT_EQ(phases, 2);
  EXPECT_EQ(skipped, 0) << worker.log_text();
  EXPECT_GE(admitted, 1);
  auto files = client->fetch(*job, dir_ / "fetched");
  ASSERT_TRUE(files.ok()) << files.status();
  std::ifstream metrics_file(dir_ / "fetched" / "metrics.json");
  const nlohmann::json metrics = nlohmann::json::parse(metrics_file);
  EXPECT_EQ(metrics["device"].get<std::string>().rfind("cuda", 0), 0u) << metrics["device"];
  EXPECT_EQ(metrics["peak_memory"]["kind"], "cuda_allocator");

  // RenderView on the trainer's GPU gives the job's own test renders (renders/, also made on the GPU), frame
  // after frame from the model the service keeps.
  auto cameras = client->job_cameras(*job);
  ASSERT_TRUE(cameras.ok()) << cameras.status();
  ASSERT_GT(cameras->test_size(), 0);
  for (int repeat = 0; repeat < 2; ++repeat) {
    for (const v1::Camera& camera : cameras->test()) {
      auto rendered = client->render(*job, camera);
      ASSERT_TRUE(rendered.ok()) << rendered.status();
      auto saved = read_image(dir_ / "fetched" / "renders" / camera.name());
      ASSERT_TRUE(saved.ok()) << saved.status();
      EXPECT_LE((*rendered - *saved).abs().max().item<float>(), 1.0f / 255 + 1e-6) << camera.name();
      EXPECT_GT(rendered->std().item<float>(), 0.01f) << camera.name();
    }
  }
}

}  // namespace
}  // namespace gaps

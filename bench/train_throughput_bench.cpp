// CPU (or CUDA) training throughput on a real scene: iterations per second of the vanilla trainer and the
// split between forward render, backward and the rest, on the benchmark protocol's views.
// With --trace, iterations [trace_at, trace_at + trace_iterations) run under the PyTorch (Kineto) profiler
// and its Chrome trace is written there; bench/trace_summary.py ranks host operations and GPU kernels.
//   train_throughput_bench --scene ../shared/data/llff/fern --views 3 --resolution 8 --iterations 500
//   train_throughput_bench --device cuda --init_ply points.ply --iterations 10000 --trace t.json --trace_at 3000
#include <chrono>
#include <fstream>
#include <iostream>
#include <optional>

#include <ATen/ATen.h>
#include <ATen/Parallel.h>
#include <nlohmann/json.hpp>
#include "absl/flags/flag.h"
#include "absl/flags/parse.h"
#include "bench/bench_scene.h"
#include "bench/kineto_trace.h"
#include "common/image_io.h"
#include "common/ply.h"
#include "gs_trainer/model/render.h"
#include "gs_trainer/pipeline.h"
#include "gs_trainer/raster/losses.h"
#include "gs_trainer/train/budget.h"

ABSL_FLAG(std::string, scene, GAPS_DATA_DIR "/llff/fern", "scene folder");
ABSL_FLAG(int, views, 3, "training views");
ABSL_FLAG(int, resolution, 8, "downscale factor");
ABSL_FLAG(int, iterations, 500, "training iterations to time");
ABSL_FLAG(int64_t, random_points, 20000, "random initial points");
ABSL_FLAG(std::string, device, "cpu", "cpu or cuda");
ABSL_FLAG(std::string, json, "", "append the result as one JSON line to this file");
ABSL_FLAG(std::string, init_ply, "", "initial points (PLY, e.g. from `gaps init`) instead of random ones");
ABSL_FLAG(std::string, trace, "", "write a profiler trace (Chrome JSON) of some iterations to this file");
ABSL_FLAG(int, trace_at, 1000, "first traced iteration");
ABSL_FLAG(int, trace_iterations, 50, "traced iterations");
ABSL_FLAG(int64_t, max_gaussians, -1,
          "Gaussian budget: -1 = the automatic budget of `gaps train`, 0 = unlimited growth, > 0 = this many");

namespace {

double seconds_since(std::chrono::steady_clock::time_point t) {
  return std::chrono::duration<double>(std::chrono::steady_clock::now() - t).count();
}

void sync(const at::Device& d) {
  if (d.is_cuda()) at::zeros({1}, at::TensorOptions().device(d)).cpu();  // waits for queued kernels
}

}  // namespace

int main(int argc, char** argv) {
  absl::ParseCommandLine(argc, argv);
  const at::Device device(absl::GetFlag(FLAGS_device));
  auto cameras_or = gaps::bench::training_cameras(absl::GetFlag(FLAGS_scene), absl::GetFlag(FLAGS_resolution),
                                                  absl::GetFlag(FLAGS_views));
  if (!cameras_or.ok()) {
    std::cerr << cameras_or.status().message() << "\n";
    return 1;
  }
  const std::vector<gaps::Camera>& cams = *cameras_or;
  std::vector<gaps::TrainingView> views;
  for (const gaps::Camera& camera : cams) {
    auto image = gaps::load_camera_image(camera);
    if (!image.ok()) {
      std::cerr << image.status().message() << "\n";
      return 1;
    }
    views.push_back({camera, image->to(device)});
  }
  double far = 0;
  for (const auto& c : cams) far = std::max(far, c.far);
  gaps::PointCloud points;
  if (const std::string ply = absl::GetFlag(FLAGS_init_ply); !ply.empty()) {
    auto read = gaps::read_point_cloud_ply(ply);
    if (!read.ok()) {
      std::cerr << read.status().message() << "\n";
      return 1;
    }
    points = *std::move(read);
  } else {
    points = gaps::random_points_in_views(cams, absl::GetFlag(FLAGS_random_points), far, 0);
  }
  gaps::TrainConfig config;
  config.iterations = absl::GetFlag(FLAGS_iterations);
  config.device = device.str();
  const int64_t max_gaussians = absl::GetFlag(FLAGS_max_gaussians);
  config.max_gaussians =
      max_gaussians >= 0 ? max_gaussians : gaps::gaussian_budget(0, config.gaussians_per_variation, views);
  const auto model = gaps::gaussians_from_points(points, 3).to(device);

  // Stage split on the initial model.
  gaps::GaussianModel probe = model;
  for (at::Tensor* p : probe.parameters()) p->requires_grad_(true);
  const int reps = 5;
  double t_fwd = 0, t_bwd = 0;
  for (int r = 0; r < reps; ++r) {
    auto t0 = std::chrono::steady_clock::now();
    auto out = gaps::render(probe, views[0].camera);
    auto loss = gaps::photometric_loss(out.rgb, views[0].image, 0.2);
    sync(device);
    t_fwd += seconds_since(t0);
    t0 = std::chrono::steady_clock::now();
    loss.backward();
    sync(device);
    t_bwd += seconds_since(t0);
  }

  gaps::Trainer trainer(model, views, config);
  const std::string trace = absl::GetFlag(FLAGS_trace);
  const int trace_begin = absl::GetFlag(FLAGS_trace_at),
            trace_end = trace_begin + absl::GetFlag(FLAGS_trace_iterations);
  std::optional<gaps::bench::KinetoTrace> profiler;
  if (!trace.empty()) profiler.emplace(/*cuda=*/true);
  double traced_seconds = 0;
  const auto start = std::chrono::steady_clock::now();
  for (int it = 0; it < config.iterations; ++it) {
    if (!trace.empty() && it == trace_begin) {
      sync(device);
      profiler->start();
    }
    const auto t0 = std::chrono::steady_clock::now();
    trainer.step();
    if (!trace.empty() && it + 1 == trace_end) {
      sync(device);
      profiler->stop_and_save(trace);
    }
    if (it >= trace_begin && it < trace_end) traced_seconds += seconds_since(t0);
  }
  sync(device);
  const double total = seconds_since(start);
  nlohmann::json j = {{"bench", "train_throughput"},
                      {"scene", absl::GetFlag(FLAGS_scene)},
                      {"views", absl::GetFlag(FLAGS_views)},
                      {"resolution", absl::GetFlag(FLAGS_resolution)},
                      {"width", views[0].camera.width},
                      {"height", views[0].camera.height},
                      {"device", device.str()},
                      {"threads", at::get_num_threads()},
                      {"iterations", config.iterations},
                      {"initial_gaussians", model.size()},
                      {"final_gaussians", trainer.model().size()},
                      {"max_gaussians", config.max_gaussians},
                      {"seconds", total},
                      {"iterations_per_second", config.iterations / total},
                      {"initial_forward_ms", 1000 * t_fwd / reps},
                      {"initial_backward_ms", 1000 * t_bwd / reps},
                      {"init", absl::GetFlag(FLAGS_init_ply).empty() ? "random" : absl::GetFlag(FLAGS_init_ply)}};
  if (!trace.empty()) {
    j["trace"] = trace;
    j["traced_iterations"] = {trace_begin, trace_end};
    j["traced_seconds_with_profiler"] = traced_seconds;
  }
  std::cout << j.dump() << "\n";
  if (const std::string path = absl::GetFlag(FLAGS_json); !path.empty())
    std::ofstream(path, std::ios::app) << j.dump() << "\n";
  return 0;
}

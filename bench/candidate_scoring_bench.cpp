// Scoring a GAPS candidate pool: the time to render and measure every candidate of the largest tier, one view at
// a time (a render and a measurement each, as before) against candidate_statistics' batches, in one run on one
// model, with the agreement of their statistics, scores and selections. --scales adds reduced-resolution
// scoring: its time and how well its scores rank like the full-resolution ones (Spearman) and how much of
// the selection it keeps.
//   candidate_scoring_bench --model run/point_cloud.ply --scene ../shared/data/mipnerf360/bonsai --views 24 \
//       --device cuda --json results.jsonl
#include <algorithm>
#include <chrono>
#include <cmath>
#include <fstream>
#include <iostream>
#include <numeric>
#include <set>

#include <ATen/ATen.h>
#include <nlohmann/json.hpp>
#include "absl/flags/flag.h"
#include "absl/flags/parse.h"
#include "bench/bench_scene.h"
#include "bench/kineto_trace.h"
#include "gs_trainer/gaps/candidate_renders.h"
#include "gs_trainer/gaps/pose.h"
#include "gs_trainer/gaps/scores.h"
#include "gs_trainer/init/initializer.h"
#include "gs_trainer/model/render.h"
#include "gs_trainer/scene/scene.h"

ABSL_FLAG(std::string, model, "", "trained Gaussians (point_cloud.ply of a `gaps train` run)");
ABSL_FLAG(std::string, scene, GAPS_DATA_DIR "/mipnerf360/bonsai", "scene folder");
ABSL_FLAG(int, views, 24, "training views (the pool is built from their pairs)");
ABSL_FLAG(int, resolution, 8, "downscale factor");
ABSL_FLAG(std::string, device, "cpu", "cpu or cuda");
ABSL_FLAG(int, repeats, 3, "timed repetitions of each way (the median is reported)");
ABSL_FLAG(std::vector<std::string>, scales, {}, "reduced scoring resolutions to compare, e.g. 0.5,0.25");
ABSL_FLAG(std::string, json, "", "append the result as one JSON line to this file");
ABSL_FLAG(std::string, trace, "",
          "also profile one batched scoring of the pool and write its Chrome trace here (bench/trace_summary.py "
          "--iterations 1 ranks its kernels)");

namespace {

void sync(const at::Device& d) {
  if (d.is_cuda()) at::zeros({1}, at::TensorOptions().device(d)).cpu();
}

template <typename F>
double median_seconds(const at::Device& device, int repeats, F&& body) {
  std::vector<double> t;
  for (int r = 0; r < repeats; ++r) {
    sync(device);
    const auto start = std::chrono::steady_clock::now();
    body();
    sync(device);
    t.push_back(std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count());
  }
  std::sort(t.begin(), t.end());
  return t[t.size() / 2];
}

std::vector<double> ranks(const std::vector<double>& v) {
  std::vector<int> order(v.size());
  std::iota(order.begin(), order.end(), 0);
  std::sort(order.begin(), order.end(), [&](int a, int b) { return v[a] < v[b]; });
  std::vector<double> r(v.size());
  for (size_t i = 0; i < order.size(); ++i) r[order[i]] = static_cast<double>(i);
  return r;
}

double spearman(const std::vector<double>& a, const std::vector<double>& b) {
  const at::Tensor ra = at::tensor(ranks(a), at::kDouble), rb = at::tensor(ranks(b), at::kDouble);
  const at::Tensor da = ra - ra.mean(), db = rb - rb.mean();
  return ((da * db).sum() / (da.square().sum() * db.square().sum()).sqrt()).item<double>();
}

}  // namespace

int main(int argc, char** argv) {
  absl::ParseCommandLine(argc, argv);
  const at::Device device(absl::GetFlag(FLAGS_device));
  auto cameras_or = gaps::bench::training_cameras(absl::GetFlag(FLAGS_scene), absl::GetFlag(FLAGS_resolution),
                                                  absl::GetFlag(FLAGS_views));
  auto model = gaps::load_gaussians_ply(absl::GetFlag(FLAGS_model));
  if (!cameras_or.ok() || !model.ok()) {
    std::cerr << (cameras_or.ok() ? model.status() : cameras_or.status()).message() << "\n";
    return 1;
  }
  const std::vector<gaps::Camera>& gt = *cameras_or;
  const gaps::GaussianModel gaussians = model->to(device);
  gaps::GapsConfig config;
  config.n_active = gaps::n_active_for(config, gaps::views_surround_scene(gt));
  const std::vector<gaps::Candidate> pool = gaps::build_candidate_pool(gt, config, -1);
  std::vector<gaps::Camera> cameras;
  for (const auto& c : pool) cameras.push_back(c.camera);

  // Scores as a phase halfway through training computes them, the GT views as the supervised ones.
  auto scores_of = [&](const at::Tensor& rows) {
    std::vector<double> s;
    for (size_t k = 0; k < pool.size(); ++k) {
      const auto m = gaps::measurements_from(rows.data_ptr<double>() + 4 * k, gaps::min_pose_distance(cameras[k], gt),
                                             gaps::min_pose_distance(cameras[k], gt), std::nullopt);
      s.push_back(gaps::score_candidate(m, 5000, 10000, config).score);
    }
    return s;
  };
  auto selection_of = [&](const std::vector<double>& s) {
    const std::vector<int> chosen = gaps::select_for_phase(pool, s, 1, config);
    return std::set<int>(chosen.begin(), chosen.end());
  };

  const int repeats = absl::GetFlag(FLAGS_repeats);
  at::Tensor one_by_one;
  const double per_view_s = median_seconds(device, repeats, [&] {
    std::vector<at::Tensor> rows;
    for (const auto& camera : cameras) {
      const gaps::RenderOutput r = gaps::render(gaussians, camera);
      const auto m = gaps::measure_render(r.rgb.clamp(0, 1), r.alpha, 0, 0, std::nullopt, config);
      rows.push_back(at::tensor({m.mean_alpha, m.entropy_mean, m.coverage, m.contrast}, at::kDouble));
    }
    one_by_one = at::stack(rows);
  });
  at::Tensor batched;
  const double batched_s =
      median_seconds(device, repeats, [&] { batched = gaps::candidate_statistics(gaussians, cameras, config); });
  const std::vector<double> reference = scores_of(one_by_one), fast = scores_of(batched);
  double max_score_diff = 0;
  for (size_t k = 0; k < pool.size(); ++k) max_score_diff = std::max(max_score_diff, std::abs(reference[k] - fast[k]));
  const std::set<int> chosen = selection_of(reference);

  nlohmann::json j = {
      {"bench", "candidate_scoring"},
      {"scene", absl::GetFlag(FLAGS_scene)},
      {"views", absl::GetFlag(FLAGS_views)},
      {"resolution", absl::GetFlag(FLAGS_resolution)},
      {"width", gt[0].width},
      {"height", gt[0].height},
      {"device", device.str()},
      {"gaussians", gaussians.size()},
      {"candidates", pool.size()},
      {"batch", gaps::candidate_batch_size(gaussians.size(), gt[0].width, gt[0].height, device, config)},
      {"one_by_one_s", per_view_s},
      {"batched_s", batched_s},
      {"speedup", per_view_s / batched_s},
      {"max_statistic_diff", (one_by_one - batched).abs().max().item<double>()},
      {"max_score_diff", max_score_diff},
      {"same_selection", selection_of(fast) == chosen},
      {"selected", chosen.size()}};
  for (const std::string& text : absl::GetFlag(FLAGS_scales)) {
    const double s = std::stod(text);
    std::vector<gaps::Camera> small;
    for (const auto& c : cameras)
      small.push_back(c.resized(std::max(1, static_cast<int>(std::lround(c.width * s))),
                                std::max(1, static_cast<int>(std::lround(c.height * s)))));
    at::Tensor rows;
    const double seconds =
        median_seconds(device, repeats, [&] { rows = gaps::candidate_statistics(gaussians, small, config); });
    const std::vector<double> scaled = scores_of(rows);
    const std::set<int> picked = selection_of(scaled);
    int kept = 0;
    for (int k : picked) kept += chosen.count(k) > 0;
    j["scaled"].push_back({{"scale", s},
                           {"seconds", seconds},
                           {"speedup_vs_batched", batched_s / seconds},
                           {"spearman_vs_full", spearman(scaled, reference)},
                           {"selection_kept", chosen.empty() ? 1.0 : double(kept) / double(chosen.size())}});
  }
  if (const std::string trace = absl::GetFlag(FLAGS_trace); !trace.empty()) {
    gaps::bench::KinetoTrace profiler(/*cuda=*/true);
    sync(device);
    profiler.start();
    gaps::candidate_statistics(gaussians, cameras, config);
    sync(device);
    profiler.stop_and_save(trace);
    j["trace"] = trace;
  }
  std::cout << j.dump() << "\n";
  if (const std::string path = absl::GetFlag(FLAGS_json); !path.empty())
    std::ofstream(path, std::ios::app) << j.dump() << "\n";
  return 0;
}

// The pseudo-view backends judged where the truth is known: a vanilla model is trained on a scene's training
// views (the protocol's split, the run's initialisation and Gaussian budget, as `gaps train --variant vanilla`)
// and at each of --iterations (the iterations of the method's diffusion phases) every backend of the arms file
// is asked for a pseudo-view at the *test* cameras, exactly as the method asks at a pseudo pose (the render there,
// its coverage-adaptive controls, the training views nearest first as references). Each image is compared with the
// held-out photograph (PSNR, SSIM, LPIPS-VGG) and judged by the admission gate against the render, as the method
// would judge it. The plain render is the baseline every backend has to beat.
//
//   generator_eval_bench --scene DIR --views 3 [--resolution 8] [--iterations 1000,5000,9500]
//       [--total_iterations 10000] [--device cuda] [--arms_file bench/configs/generator_eval.json] [--arms a,b]
//       [--restore_weights F] [--sdxl_weights DIR] [--lpips_weights F|none] [--images DIR] [--out FILE.jsonl]
//
// One JSON line per (iteration, arm): the setting, the means over the test views and per view the pose distance
// to the nearest training camera (in units of the training cameras' median nearest-neighbour distance), the
// render's coverage, the metrics and the gate's decision with its numbers. --images writes, per iteration, a strip
// for each of the first --image_views test views: photograph | render | each arm's image.
#include <algorithm>
#include <chrono>
#include <cmath>
#include <fstream>
#include <iostream>
#include <memory>
#include <optional>
#include <string>
#include <vector>

#include <ATen/ATen.h>
#include <ATen/core/grad_mode.h>
#include <nlohmann/json.hpp>
#include "absl/flags/flag.h"
#include "absl/flags/parse.h"
#include "absl/strings/numbers.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_split.h"
#include "common/cache_dir.h"
#include "common/device.h"
#include "common/image_io.h"
#include "common/status_macros.h"
#include "diffusion_worker/backend_registry.h"
#include "gs_trainer/eval/lpips.h"
#include "gs_trainer/eval/metrics.h"
#include "gs_trainer/gaps/admission.h"
#include "gs_trainer/gaps/pose.h"
#include "gs_trainer/gaps/training.h"
#include "gs_trainer/model/render.h"
#include "gs_trainer/pipeline.h"
#include "gs_trainer/run/initial_model.h"
#include "gs_trainer/run/inputs.h"

ABSL_FLAG(std::string, scene, GAPS_DATA_DIR "/llff/fern", "scene folder");
ABSL_FLAG(int, views, 3, "training views");
ABSL_FLAG(int, resolution, 8, "downscale factor");
ABSL_FLAG(std::string, init, "auto", "initialisation method, as gaps train --init");
ABSL_FLAG(std::string, init_cache, "",
          "initial point cloud cache (empty: gaps train's, $GAPS_CACHE/init; none: no cache)");
ABSL_FLAG(std::string, iterations, "1000,5000,9500", "iterations at which the backends are asked (ascending)");
ABSL_FLAG(int, total_iterations, 10000, "the run's length (its schedules: learning rates, densification)");
ABSL_FLAG(std::string, device, "cpu", "device of training, rendering, LPIPS and the backends that use one");
ABSL_FLAG(uint64_t, seed, 0, "training seed; request k of an evaluation gets seed + k");
ABSL_FLAG(std::string, arms_file, GAPS_SOURCE_DIR "/bench/configs/generator_eval.json", "the arms (backends)");
ABSL_FLAG(std::string, arms, "", "comma-separated arm names to run (empty: every arm of the file)");
ABSL_FLAG(std::string, restore_weights, "", "Real-ESRGAN x4plus safetensors for restore arms (empty: default)");
ABSL_FLAG(std::string, sdxl_weights, GAPS_SOURCE_DIR "/tests/fixtures/sdxl_tiny/model",
          "diffusers SDXL folder for sdxl arms (default: the tiny random-weight test model)");
ABSL_FLAG(std::string, lpips_weights, "", "LPIPS-VGG safetensors (empty: the set-up's file; none: no LPIPS)");
ABSL_FLAG(int, lora_steps, gaps::GapsConfig().lora_steps,
          "scene adaptation steps of the backends that adapt (sdxl: LoRA on the training views), as the method asks");
ABSL_FLAG(int, max_test_views, 0, "evaluate at most this many test views (0: all)");
ABSL_FLAG(std::string, images, "", "folder for the comparison strips (empty: none)");
ABSL_FLAG(int, image_views, 1, "strips of this many test views (the first ones) per iteration");
ABSL_FLAG(std::string, out, "", "JSON lines are appended here (empty: standard output only)");

namespace gaps {
namespace {

using Json = nlohmann::json;
using Clock = std::chrono::steady_clock;

struct Arm {
  std::string name;
  std::string backend;  // empty: the plain render
  Json options = Json::object();
  std::unique_ptr<Generator> generator;
};

// The arms of the file, those named in `only` when it is not empty (each must exist).
absl::StatusOr<std::vector<Arm>> read_arms(const std::string& path, const std::string& only) {
  std::ifstream in(path);
  if (!in) return absl::NotFoundError(absl::StrCat("arms file not found: ", path));
  const Json file = Json::parse(in, nullptr, /*allow_exceptions=*/false);
  if (file.is_discarded() || !file.contains("arms"))
    return absl::InvalidArgumentError(absl::StrCat(path, ": not a JSON object with \"arms\""));
  std::vector<Arm> all;
  for (const Json& a : file.at("arms"))
    all.push_back({a.at("name").get<std::string>(), a.value("backend", ""), a.value("options", Json::object()), {}});
  if (only.empty()) return all;
  std::vector<Arm> chosen;
  const std::vector<std::string> names = absl::StrSplit(only, ',');
  for (const std::string& name : names) {
    auto it = std::find_if(all.begin(), all.end(), [&](const Arm& a) { return a.name == name; });
    if (it == all.end()) return absl::InvalidArgumentError(absl::StrCat("no arm '", name, "' in ", path));
    chosen.push_back(std::move(*it));
    all.erase(it);
  }
  return chosen;
}

// The arm's backend with the benchmark's device and weights filled in where the arm leaves them.
absl::Status make_backend(Arm& arm, const std::string& device) {
  if (arm.backend.empty()) return absl::OkStatus();
  Json options = arm.options;
  if (generator_backend_uses_device(arm.backend) && !options.contains("device")) options["device"] = device;
  if (arm.backend == "restore" && !options.contains("weights") && !absl::GetFlag(FLAGS_restore_weights).empty())
    options["weights"] = absl::GetFlag(FLAGS_restore_weights);
  if (arm.backend == "sdxl" && !options.contains("weights")) options["weights"] = absl::GetFlag(FLAGS_sdxl_weights);
  arm.options = options;
  GAPS_ASSIGN_OR_RETURN(arm.generator, make_generator(arm.backend, options.dump()));
  return absl::OkStatus();
}

absl::StatusOr<std::vector<int>> parse_iterations(const std::string& text, int total) {
  std::vector<int> out;
  for (const absl::string_view part : absl::StrSplit(text, ',')) {
    int it = 0;
    if (!absl::SimpleAtoi(part, &it) || it < 1 || it > total || (!out.empty() && it <= out.back()))
      return absl::InvalidArgumentError(
          absl::StrCat("--iterations: '", text, "' is not an ascending list of iterations in [1, ", total, "]"));
    out.push_back(it);
  }
  return out;
}

// Where a test camera stands relative to the training cameras: its distance to the nearest one over the median
// distance between a training camera and its nearest neighbour (1 = about one training baseline away).
std::vector<double> relative_pose_distances(const std::vector<Camera>& test, const std::vector<Camera>& train) {
  std::vector<double> spacing;
  for (size_t i = 0; i < train.size(); ++i) {
    std::vector<Camera> others = train;
    others.erase(others.begin() + static_cast<long>(i));
    if (!others.empty()) spacing.push_back(min_pose_distance(train[i], others));
  }
  std::sort(spacing.begin(), spacing.end());
  const double unit = spacing.empty() ? 1.0 : std::max(spacing[spacing.size() / 2], 1e-12);
  std::vector<double> out;
  for (const Camera& c : test) out.push_back(min_pose_distance(c, train) / unit);
  return out;
}

// The training views with the model's renders there, ordered nearest first to `pose` (as the method sends them).
// What every arm is judged at: the test views, their renders and the requests the method would send.
struct Probes {
  std::vector<TrainingView> test;
  std::vector<RenderOutput> renders;
  std::vector<GenerationRequest> requests;
};

Probes probes_at(const GaussianModel& model, const std::vector<TrainingView>& train,
                 const std::vector<TrainingView>& test, const GapsConfig& c, uint64_t seed) {
  at::AutoGradMode no_grad(false);
  Probes p{test, render_views(model, cameras_of(test)), {}};
  const std::vector<ReferenceView> refs = reference_views(model, train);
  for (size_t k = 0; k < test.size(); ++k) {
    RenderOutput cpu{p.renders[k].rgb.cpu(), p.renders[k].depth.cpu(), p.renders[k].alpha.cpu()};
    p.requests.push_back(generation_request(test[k].camera, cpu,
                                            nearest_first(test[k].camera, refs, c.pose_rotation_weight), c, seed + k));
  }
  return p;
}

Json metrics_json(const ImageMetrics& m) {
  Json j = {{"psnr", m.psnr}, {"ssim", m.ssim}, {"lpips", nullptr}};
  if (m.lpips) j["lpips"] = *m.lpips;
  return j;
}

// One arm at every probe: per view its metrics against the photograph and (for a backend) the gate's decision.
struct ArmResult {
  Json row;
  std::vector<at::Tensor> images;
};

absl::StatusOr<ArmResult> evaluate_arm(Arm& arm, const Probes& p, const std::vector<double>& distances,
                                       const GapsConfig& c, const Lpips* lpips) {
  ArmResult r;
  const auto start = Clock::now();
  if (arm.generator) {
    GAPS_ASSIGN_OR_RETURN(r.images, arm.generator->generate(p.requests));
    if (r.images.size() != p.requests.size())
      return absl::InternalError(absl::StrCat(arm.name, ": ", r.images.size(), " images for ", p.requests.size()));
  } else {
    for (const RenderOutput& render : p.renders) r.images.push_back(render.rgb.clamp(0, 1));
  }
  const double seconds = std::chrono::duration<double>(Clock::now() - start).count();
  at::AutoGradMode no_grad(false);
  std::vector<ImageMetrics> all;
  Json views = Json::array();
  int admitted = 0;
  for (size_t k = 0; k < r.images.size(); ++k) {
    const at::Device device = p.test[k].image.device();
    const at::Tensor image = r.images[k].to(device, at::kFloat);
    all.push_back(evaluate_image(image, p.test[k].image, lpips));
    Json v = metrics_json(all.back());
    v["view"] = k;
    v["pose_distance"] = distances[k];
    v["coverage"] = p.requests[k].coverage;
    v["strength"] = p.requests[k].strength;
    if (arm.generator) {
      const RenderOutput& render = p.renders[k];
      const AdmissionDecision d =
          admit_pseudo_view(image, render.rgb.clamp(0, 1), render.alpha, c, p.requests[k].strength);
      admitted += d.admitted;
      v["admitted"] = d.admitted;
      v["residual"] = d.mean_residual;
      v["structure"] = d.structure ? Json(*d.structure) : Json(nullptr);
      v["u2"] = uncertainty_variance(d.uncertainty);
      v["reason"] = d.reason;
    }
    views.push_back(v);
  }
  GAPS_ASSIGN_OR_RETURN(const ImageMetrics mean, average_metrics(all));
  r.row = metrics_json(mean);
  r.row["arm"] = arm.name;
  r.row["backend"] = arm.backend.empty() ? Json(nullptr) : Json(arm.backend);
  r.row["options"] = arm.options;
  r.row["admitted"] = arm.generator ? Json(admitted) : Json(nullptr);
  r.row["generate_seconds"] = seconds;
  r.row["per_view"] = views;
  return r;
}

// One strip per test view: photograph | render | each arm's image (the arms after "render").
absl::Status write_strips(const std::filesystem::path& dir, int iteration, const Probes& p,
                          const std::vector<std::vector<at::Tensor>>& images) {
  std::vector<std::pair<std::filesystem::path, at::Tensor>> files;
  const size_t views = std::min<size_t>(p.test.size(), std::max(0, absl::GetFlag(FLAGS_image_views)));
  for (size_t k = 0; k < views; ++k) {
    std::vector<at::Tensor> row = {p.test[k].image.cpu(), p.renders[k].rgb.clamp(0, 1).cpu()};
    for (const auto& arm_images : images) row.push_back(arm_images[k].cpu().to(at::kFloat));
    files.push_back({dir / absl::StrCat("it", iteration, "_view", k, ".png"), at::cat(row, 1)});
  }
  std::error_code ec;
  std::filesystem::create_directories(dir, ec);
  if (ec) return absl::InternalError(absl::StrCat("cannot create ", dir.string(), ": ", ec.message()));
  return write_pngs(files);
}

struct Setting {
  RunOptions options;
  LoadedScene loaded;
  std::vector<TrainingView> test;
  std::optional<Lpips> lpips;
  Json header;
};

RunOptions run_options() {
  RunOptions o;
  o.scene_dir = absl::GetFlag(FLAGS_scene);
  o.views = absl::GetFlag(FLAGS_views);
  o.resolution = absl::GetFlag(FLAGS_resolution);
  o.init = absl::GetFlag(FLAGS_init);
  const std::string cache = absl::GetFlag(FLAGS_init_cache);
  if (cache.empty() && !gaps_cache_dir().empty()) o.init_cache_dir = gaps_cache_dir() / "init";
  if (!cache.empty() && cache != "none") o.init_cache_dir = cache;
  o.config.iterations = absl::GetFlag(FLAGS_total_iterations);
  o.config.device = absl::GetFlag(FLAGS_device);
  o.config.seed = absl::GetFlag(FLAGS_seed);
  const std::string lpips = absl::GetFlag(FLAGS_lpips_weights);
  o.lpips_weights =
      lpips.empty() ? default_lpips_weights_path() : std::filesystem::path(lpips == kLpipsOff ? "" : lpips);
  return o;
}

absl::StatusOr<Setting> load_setting(const RunLog& log) {
  Setting s;
  s.options = run_options();
  GAPS_RETURN_IF_ERROR(check_device(s.options.config.device));
  GAPS_RETURN_IF_ERROR(check_scene(s.options));
  const at::Device device(s.options.config.device);
  GAPS_ASSIGN_OR_RETURN(s.lpips, run_lpips(s.options, device));
  GAPS_ASSIGN_OR_RETURN(s.loaded, load_scene_and_training_views(s.options, device, log));
  std::vector<int> test_indices = s.loaded.split.test;
  const int cap = absl::GetFlag(FLAGS_max_test_views);
  if (cap > 0 && static_cast<int>(test_indices.size()) > cap) test_indices.resize(cap);
  GAPS_ASSIGN_OR_RETURN(s.test, load_views(s.loaded.scene, test_indices, device));
  s.options = budgeted_options(s.options, s.loaded.train, log);
  s.header = {{"bench", "generator_eval"},     {"scene", s.options.scene_dir.filename().string()},
              {"views", s.options.views},      {"resolution", s.options.resolution},
              {"seed", s.options.config.seed}, {"device", s.options.config.device},
              {"test_views", s.test.size()},   {"total_iterations", s.options.config.iterations}};
  return s;
}

absl::Status emit(const Json& row) {
  std::cout << row.dump() << std::endl;
  const std::string path = absl::GetFlag(FLAGS_out);
  if (path.empty()) return absl::OkStatus();
  std::ofstream out(path, std::ios::app);
  out << row.dump() << "\n";
  if (!out) return absl::InternalError(absl::StrCat("cannot append to ", path));
  return absl::OkStatus();
}

absl::Status run() {
  const RunLog log = [](const std::string& line) { std::cerr << "generator_eval: " << line << "\n"; };
  GAPS_ASSIGN_OR_RETURN(std::vector<Arm> arms, read_arms(absl::GetFlag(FLAGS_arms_file), absl::GetFlag(FLAGS_arms)));
  GAPS_ASSIGN_OR_RETURN(Setting s, load_setting(log));
  GAPS_ASSIGN_OR_RETURN(const std::vector<int> stops,
                        parse_iterations(absl::GetFlag(FLAGS_iterations), s.options.config.iterations));
  for (Arm& arm : arms) GAPS_RETURN_IF_ERROR(make_backend(arm, s.options.config.device));
  InitRecord init;
  GAPS_ASSIGN_OR_RETURN(GaussianModel initial, initial_model(s.options, s.loaded.scene, s.loaded.train, log, &init));
  s.header["init"] = init.method;
  const GapsConfig c;
  const std::vector<ReferenceView> gt_refs = reference_views(initial, s.loaded.train);
  for (Arm& arm : arms)
    if (arm.generator)
      GAPS_RETURN_IF_ERROR(
          arm.generator->adapt(gt_refs, SceneAdaptation{c.lora_rank, absl::GetFlag(FLAGS_lora_steps)}));
  const std::vector<double> distances = relative_pose_distances(cameras_of(s.test), cameras_of(s.loaded.train));
  Trainer trainer(initial.to(at::Device(s.options.config.device)), s.loaded.train, s.options.config);
  for (int stop : stops) {
    while (trainer.iteration() < stop) trainer.step();
    const Probes p = probes_at(trainer.model(), s.loaded.train, s.test, c, s.options.config.seed);
    std::vector<std::vector<at::Tensor>> strips;
    for (Arm& arm : arms) {
      GAPS_ASSIGN_OR_RETURN(ArmResult r, evaluate_arm(arm, p, distances, c, s.lpips ? &*s.lpips : nullptr));
      Json row = s.header;
      row["iteration"] = stop;
      row["gaussians"] = trainer.model().size();
      row.update(r.row);
      GAPS_RETURN_IF_ERROR(emit(row));
      if (arm.generator) strips.push_back(std::move(r.images));
    }
    if (!absl::GetFlag(FLAGS_images).empty())
      GAPS_RETURN_IF_ERROR(write_strips(absl::GetFlag(FLAGS_images), stop, p, strips));
  }
  return absl::OkStatus();
}

}  // namespace
}  // namespace gaps

int main(int argc, char** argv) {
  absl::ParseCommandLine(argc, argv);
  const absl::Status st = gaps::run();
  if (!st.ok()) {
    std::cerr << "generator_eval_bench: " << st << "\n";
    return 1;
  }
  return 0;
}

// SDXL speed on the GPU: the full-size SDXL base UNet (2.6B parameters, random weights) per denoising
// step, and a whole img2img (30-step schedule at strength 0.5: 15 UNet steps with classifier-free
// guidance, VAE encode and decode, prompt encoding), in fp16, at 1024 x 1024 and at the LLFF `-r 8`
// pseudo-view size 504 x 378, which runs padded (bottom edge, replicated) to 504 x 384 so that the
// latents (63 x 48) are whole. The UNet step runs on a batch of 2 (unconditional + conditional), eagerly
// and replayed from a CUDA graph. Random weights are written once to --model_dir (diffusers layout,
// safetensors) so that bench/sdxl_diffusers_bench.py times diffusers on identical weights
// (bench/sdxl_side_by_side.sh runs both). One JSON line per measurement, with peak GPU memory.
//   sdxl_bench --model_dir DIR [--write_model] [--runs 10] [--json results.jsonl]
// Without CUDA it only writes the folder (if asked) and exits with status 2 and a message.
#include <algorithm>
#include <chrono>
#include <filesystem>
#include <fstream>
#include <functional>
#include <iostream>
#include <string>
#include <vector>

#include <ATen/ATen.h>
#include <c10/core/InferenceMode.h>
#include <torch/headeronly/version.h>
#include <nlohmann/json.hpp>
#include "absl/flags/flag.h"
#include "absl/flags/parse.h"
#include "bench/random_sdxl_folder.h"
#include "diffusion_worker/sdxl/pipeline.h"

#if defined(GAPS_CUDA_KERNELS)
#include <ATen/cuda/CUDAContext.h>
#include <ATen/cuda/CUDAGraph.h>
#include <c10/cuda/CUDACachingAllocator.h>
#include <c10/cuda/CUDAGuard.h>
#include <c10/cuda/CUDAStream.h>
#endif

ABSL_FLAG(std::string, model_dir, "/tmp/gaps_sdxl_random", "random-weight SDXL folder (written with --write_model)");
ABSL_FLAG(bool, write_model, false, "write the random-weight folder first when it has no model_index.json");
ABSL_FLAG(std::string, configs_from, "",
          "take the component configs from this SDXL folder instead of SDXL base 1.0 "
          "(e.g. the tiny test model, for a smoke test of the writer and of sdxl_diffusers_bench.py)");
ABSL_FLAG(uint64_t, weights_seed, 0, "seed of the random weights");
ABSL_FLAG(std::string, dtype, "float16", "float16 or bfloat16");
ABSL_FLAG(int, runs, 10, "timed UNet steps per case (median reported)");
ABSL_FLAG(int, img2img_runs, 3, "timed img2img runs per size (median reported)");
ABSL_FLAG(int, steps, 30, "img2img schedule length");
ABSL_FLAG(double, strength, 0.5, "img2img strength");
ABSL_FLAG(double, guidance, 5.0, "classifier-free guidance scale");
ABSL_FLAG(bool, cuda_graph, true, "also time the UNet step replayed from a CUDA graph");
ABSL_FLAG(std::string, json, "", "also append the JSON lines to this file");

namespace {

struct Size {
  const char* name;
  int64_t width, height;          // the view
  int64_t run_width, run_height;  // padded to a multiple of 8
};

#if defined(GAPS_CUDA_KERNELS)
void device_sync() { at::cuda::getCurrentCUDAStream().synchronize(); }
void reset_peak() { c10::cuda::CUDACachingAllocator::resetPeakStats(0); }
double peak_gib() {
  const auto stats = c10::cuda::CUDACachingAllocator::getDeviceStats(0);
  return static_cast<double>(stats.allocated_bytes[0].peak) / (1024.0 * 1024.0 * 1024.0);
}
#endif

struct Timing {
  double median_ms, min_ms;
};

Timing time_ms(int warmup, int runs, const std::function<void()>& f) {
#if defined(GAPS_CUDA_KERNELS)
  for (int i = 0; i < warmup; ++i) f();
  device_sync();
  std::vector<double> ms;
  for (int i = 0; i < runs; ++i) {
    const auto t0 = std::chrono::steady_clock::now();
    f();
    device_sync();
    ms.push_back(std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - t0).count());
  }
  std::sort(ms.begin(), ms.end());
  return {ms[ms.size() / 2], ms.front()};
#else
  (void)warmup, (void)runs, (void)f;
  return {0, 0};
#endif
}

void emit(const nlohmann::json& j) {
  std::cout << j.dump() << std::endl;
  const std::string path = absl::GetFlag(FLAGS_json);
  if (!path.empty()) std::ofstream(path, std::ios::app) << j.dump() << "\n";
}

#if defined(GAPS_CUDA_KERNELS)
gaps::sdxl::UNetInputs unet_inputs(const Size& s, at::ScalarType dtype) {
  const auto opts = at::TensorOptions().device(at::kCUDA).dtype(dtype);
  at::manual_seed(3);
  gaps::sdxl::UNetInputs in;
  in.sample = at::randn({2, 4, s.run_height / 8, s.run_width / 8}, opts);
  in.timestep = at::scalar_tensor(500.0, at::TensorOptions().device(at::kCUDA));
  in.encoder_hidden_states = at::randn({2, 77, 2048}, opts);
  in.text_embeds = at::randn({2, 1280}, opts);
  const auto h = static_cast<float>(s.run_height), w = static_cast<float>(s.run_width);
  in.time_ids = at::tensor(std::vector<float>{h, w, 0, 0, h, w, h, w, 0, 0, h, w}).view({2, 6}).to(at::kCUDA);
  return in;
}

Timing unet_graph_ms(const gaps::sdxl::UNet2DCondition& unet, const gaps::sdxl::UNetInputs& in, int runs) {
  at::cuda::CUDAGraph graph;
  at::Tensor out;
  const c10::cuda::CUDAStream stream = c10::cuda::getStreamFromPool();
  {
    c10::cuda::CUDAStreamGuard guard(stream);
    for (int i = 0; i < 2; ++i) out = unet.forward(in);  // warm-up on the capture stream
    stream.synchronize();
    graph.capture_begin();
    out = unet.forward(in);
    graph.capture_end();
  }
  return time_ms(3, runs, [&] { graph.replay(); });
}

// Times the whole img2img at each size, eagerly or replaying UNet graphs; false (with a message) on error.
bool time_img2img(gaps::sdxl::SdxlPipeline& pipeline, const std::vector<Size>& sizes, bool graphs,
                  const nlohmann::json& common) {
  if (const absl::Status s = pipeline.set_cuda_graphs(graphs); !s.ok()) {
    std::cerr << "sdxl_bench: " << s << "\n";
    return false;
  }
  gaps::sdxl::Img2ImgParams params;
  params.steps = absl::GetFlag(FLAGS_steps);
  params.strength = absl::GetFlag(FLAGS_strength);
  params.guidance_scale = absl::GetFlag(FLAGS_guidance);
  for (const Size& s : sizes) {
    at::manual_seed(4);
    const at::Tensor view = at::rand({1, 3, s.height, s.width});
    const at::Tensor image = at::replication_pad2d(view, {0, s.run_width - s.width, 0, s.run_height - s.height});
    reset_peak();
    absl::Status failure;
    const Timing t = time_ms(1, absl::GetFlag(FLAGS_img2img_runs), [&] {
      auto out = pipeline.img2img(image, {"a photo of a fern in a garden"}, params, {1234});
      if (!out.ok()) failure = out.status();
    });
    if (!failure.ok()) {
      std::cerr << "sdxl_bench: img2img failed: " << failure << "\n";
      return false;
    }
    nlohmann::json j = common;
    j["case"] = "img2img";
    j["cuda_graphs"] = graphs;
    j["size"] = s.name;
    j["run_size"] = {s.run_width, s.run_height};
    j["steps"] = params.steps;
    j["strength"] = params.strength;
    j["unet_steps"] = static_cast<int>(params.steps * params.strength);
    j["guidance"] = params.guidance_scale;
    j["ms"] = t.median_ms;
    j["min_ms"] = t.min_ms;
    j["peak_gpu_memory_gib"] = peak_gib();
    emit(j);
  }
  return true;
}
#endif

}  // namespace

int main(int argc, char** argv) {
  absl::ParseCommandLine(argc, argv);
  const std::string dir = absl::GetFlag(FLAGS_model_dir);
  if (!gaps::bench::ensure_random_sdxl(dir, absl::GetFlag(FLAGS_write_model), absl::GetFlag(FLAGS_configs_from),
                                       absl::GetFlag(FLAGS_weights_seed), "sdxl_bench")) {
    return 1;
  }
#if !defined(GAPS_CUDA_KERNELS)
  std::cerr << "sdxl_bench: this build has no CUDA (configured with GAPS_CUDA=OFF or without nvcc); the full-size "
               "SDXL timings need a CUDA GPU and a CUDA build.\n";
  return 2;
#else
  if (!at::hasCUDA()) {
    std::cerr << "sdxl_bench: no CUDA device found; the full-size SDXL timings (fp16, about 7 GB of weights) "
                 "run on a GPU only.\n";
    return 2;
  }
  const std::string dtype_name = absl::GetFlag(FLAGS_dtype);
  if (dtype_name != "float16" && dtype_name != "bfloat16") {
    std::cerr << "sdxl_bench: --dtype must be float16 or bfloat16\n";
    return 2;
  }
  const at::ScalarType dtype = dtype_name == "float16" ? at::kHalf : at::kBFloat16;

  c10::InferenceMode inference;
  // The caching allocator's statistics exist only once CUDA has allocated through it.
  at::empty({1}, at::TensorOptions().device(at::kCUDA));
  nlohmann::json common;
  common["bench"] = "sdxl";
  common["impl"] = "gaps-libtorch";
  common["gpu"] = at::cuda::getDeviceProperties(0)->name;
  common["torch"] = TORCH_VERSION;
  common["dtype"] = dtype_name;

  reset_peak();
  const auto t0 = std::chrono::steady_clock::now();
  auto pipeline = gaps::sdxl::SdxlPipeline::load(dir, gaps::sdxl::PipelineOptions{dtype, at::Device(at::kCUDA), ""});
  if (!pipeline.ok()) {
    std::cerr << "sdxl_bench: " << pipeline.status() << "\n";
    return 1;
  }
  device_sync();
  nlohmann::json load = common;
  load["case"] = "load";
  load["seconds"] = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  load["gpu_memory_gib"] = peak_gib();
  emit(load);

  const std::vector<Size> sizes{{"1024x1024", 1024, 1024, 1024, 1024}, {"504x378", 504, 378, 504, 384}};
  const int runs = absl::GetFlag(FLAGS_runs);
  for (const Size& s : sizes) {
    const gaps::sdxl::UNetInputs in = unet_inputs(s, dtype);
    nlohmann::json j = common;
    j["case"] = "unet_step";
    j["size"] = s.name;
    j["run_size"] = {s.run_width, s.run_height};
    j["latent"] = {s.run_width / 8, s.run_height / 8};
    j["batch"] = 2;
    j["runs"] = runs;
    reset_peak();
    at::Tensor out;
    const Timing eager = time_ms(3, runs, [&] { out = (*pipeline)->unet().forward(in); });
    j["eager_ms"] = eager.median_ms;
    j["eager_min_ms"] = eager.min_ms;
    j["output_finite"] = out.isfinite().all().item<bool>();
    j["peak_gpu_memory_gib"] = peak_gib();
    if (absl::GetFlag(FLAGS_cuda_graph)) {
      const Timing graph = unet_graph_ms((*pipeline)->unet(), in, runs);
      j["cuda_graph_ms"] = graph.median_ms;
      j["cuda_graph_min_ms"] = graph.min_ms;
    }
    emit(j);
  }
  for (const bool graphs : {false, true}) {
    if (graphs && !absl::GetFlag(FLAGS_cuda_graph)) break;
    if (!time_img2img(**pipeline, sizes, graphs, common)) return 1;
  }
  return 0;
#endif
}

// Speed and GPU memory of the sdxl backend's models with every component at full size (random weights):
//   lora_training          scene adaptation: 50 Adam steps of LoRA (rank 4, to_q/k/v/out) on three 504 x 378
//                          views with their depth ControlNet (SdxlPipeline::train_lora, what adapt() runs),
//                          eager and (on CUDA) replayed from a CUDA graph, side by side;
//   img2img_controlnet_lora
//                          a pseudo-view: ControlNet depth + LoRA img2img (30-step schedule at strength 0.6,
//                          guidance 5, conditioning scale 1);
//   img2img_controlnet_ip, img2img_controlnet_ip_lora
//                          the same with the IP-Adapter (ViT-H image encoder, scale 0.5) and its reference
//                          image, without and with the LoRA loaded;
//   inpaint                the two-stage path's second stage: SD2 inpainting from pure noise (30 DDIM steps,
//                          guidance 7.5) under a mask;
//   depth_anything         Depth-Anything V2 on one view (estimate_depth, as the backend's LoRA conditioning);
//   worker_peak            the caching allocator's peak with SDXL + ControlNet + IP-Adapter + CLIP vision +
//                          LoRA + SD2 inpainting + Depth-Anything loaded, over all the cases run with them.
// Pseudo-view sizes 504 x 378 (LLFF -r 8, padded at the bottom, replicated, to 504 x 384) and 1024 x 1024.
// Medians of --runs after --warmup, synchronised with the device. One JSON line per measurement. The SDXL
// folder comes from --write_model (as sdxl_bench); the other components from
// bench/make_random_generator_weights.py; bench/generator_diffusers_bench.py times diffusers on the same
// files and bench/generator_side_by_side.sh runs all of it.
//   generator_bench --sdxl_dir DIR --weights_dir DIR [--write_model [--write_only]] [--json out.jsonl]
// On the CPU (--device cpu --dtype float32, e.g. with the --tiny weights) it runs the same code, without
// memory figures.
#include <algorithm>
#include <chrono>
#include <fstream>
#include <functional>
#include <iostream>
#include <memory>
#include <numeric>
#include <optional>
#include <string>
#include <vector>

#include <ATen/ATen.h>
#include <torch/headeronly/version.h>
#include <nlohmann/json.hpp>
#include "absl/flags/flag.h"
#include "absl/flags/parse.h"
#include "absl/strings/numbers.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_split.h"
#include "bench/kineto_trace.h"
#include "bench/random_sdxl_folder.h"
#include "diffusion_worker/depth/depth_anything.h"
#include "diffusion_worker/sdxl/inpaint_pipeline.h"
#include "diffusion_worker/sdxl/pipeline.h"

#if defined(GAPS_CUDA_KERNELS)
#include <ATen/cuda/CUDAContext.h>
#include <c10/cuda/CUDACachingAllocator.h>
#include <c10/cuda/CUDAFunctions.h>
#endif

ABSL_FLAG(std::string, sdxl_dir, "/tmp/gaps_sdxl_random", "random-weight SDXL folder (written with --write_model)");
ABSL_FLAG(std::string, weights_dir, "/tmp/gaps_generator_random",
          "the other components (bench/make_random_generator_weights.py)");
ABSL_FLAG(bool, write_model, false, "write the SDXL folder first when it has no model_index.json");
ABSL_FLAG(bool, write_only, false, "only write the SDXL folder (with --write_model), then exit");
ABSL_FLAG(std::string, configs_from, "", "take the SDXL component configs from this folder instead of SDXL base 1.0");
ABSL_FLAG(uint64_t, weights_seed, 0, "seed of the random SDXL weights");
ABSL_FLAG(std::string, device, "cuda", "cuda or cpu");
ABSL_FLAG(std::string, dtype, "float16", "float16, bfloat16 or float32 (the CPU runs float32 only)");
ABSL_FLAG(std::string, vae_dtype, "",
          "the VAE's type: \"\" = float32 (SDXL's config asks for force_upcast), bfloat16, float16 or float32");
ABSL_FLAG(std::string, sizes, "504x378,1024x1024", "pseudo-view sizes WxH, padded to the latent factor");
ABSL_FLAG(std::string, lora_size, "504x378", "size of the LoRA training views");
ABSL_FLAG(std::string, batches, "1",
          "pseudo-views per img2img call, comma-separated (the worker's batch_size); each case's line gives "
          "the call's time and the time per view");
ABSL_FLAG(int, runs, 3, "timed runs per case (median reported)");
ABSL_FLAG(int, warmup, 1, "untimed runs before them");
ABSL_FLAG(int, steps, 30, "img2img schedule length");
ABSL_FLAG(double, strength, 0.6, "img2img strength");
ABSL_FLAG(double, guidance, 5.0, "classifier-free guidance scale of img2img");
ABSL_FLAG(double, control_scale, 1.0, "ControlNet conditioning scale");
ABSL_FLAG(double, ip_scale, 0.5, "IP-Adapter scale (lambda_ip)");
ABSL_FLAG(int, lora_steps, 50, "LoRA training steps");
ABSL_FLAG(int, lora_views, 3, "LoRA training views");
ABSL_FLAG(int, lora_rank, 4, "LoRA rank (alpha = rank)");
ABSL_FLAG(int, inpaint_steps, 30, "SD2 inpainting steps (strength 1)");
ABSL_FLAG(double, inpaint_guidance, 7.5, "SD2 inpainting guidance scale");
ABSL_FLAG(std::string, inpaint_scheduler, "", "\"\" = the folder's (DDIM); euler | ddim | dpmpp2m");
ABSL_FLAG(bool, cuda_graphs, false, "replay the SDXL UNet from CUDA graphs (the backend's cuda_graphs option)");
ABSL_FLAG(bool, channels_last, false,
          "convolutions and activations in channels-last order (the backend's channels_last option)");
ABSL_FLAG(std::string, commit, "", "the commit measured, recorded in every line");
ABSL_FLAG(std::string, json, "", "also append the JSON lines to this file");
ABSL_FLAG(std::string, phases, "lora,worker",
          "which to run: lora (LoRA training, ControlNet + LoRA img2img), worker (the other cases), or both");
ABSL_FLAG(std::string, lora_trace, "",
          "after the timed LoRA training, run --lora_trace_steps more steps under the PyTorch (Kineto) profiler "
          "and write its Chrome trace here (bench/trace_summary.py TRACE --iterations N ranks it)");
ABSL_FLAG(int, lora_trace_steps, 5, "LoRA training steps in the trace");
ABSL_FLAG(bool, cudnn_benchmark, false, "let cuDNN time its convolution algorithms (recorded in every line)");
ABSL_FLAG(std::string, img2img_trace, "",
          "after timing img2img_controlnet_ip_lora (the four constraints), run one more call at the last size and "
          "batch under the profiler and write its Chrome trace here (bench/trace_summary.py TRACE --iterations 1)");

namespace {

namespace sdxl = gaps::sdxl;
namespace depth = gaps::depth;

constexpr char kPrompt[] = "a photo of a fern in a garden";

struct Size {
  std::string name;
  int64_t width, height;          // the view
  int64_t run_width, run_height;  // padded to the latent factor
};

std::optional<Size> parse_size(const std::string& text, int64_t factor) {
  const std::vector<std::string> parts = absl::StrSplit(text, 'x');
  int64_t w = 0, h = 0;
  if (parts.size() != 2 || !absl::SimpleAtoi(parts[0], &w) || !absl::SimpleAtoi(parts[1], &h) || w < 1 || h < 1) {
    return std::nullopt;
  }
  return Size{text, w, h, (w + factor - 1) / factor * factor, (h + factor - 1) / factor * factor};
}

class Device {
 public:
  // "cuda" without an index means the current device; the allocator's statistics need the index itself.
  explicit Device(at::Device device) : device_(with_index(device)) {}
  const at::Device& device() const { return device_; }
  void sync() const {
#if defined(GAPS_CUDA_KERNELS)
    if (device_.is_cuda()) at::cuda::getCurrentCUDAStream().synchronize();
#endif
  }
  void reset_peak() const {
#if defined(GAPS_CUDA_KERNELS)
    if (device_.is_cuda()) c10::cuda::CUDACachingAllocator::resetPeakStats(device_.index());
#endif
  }
  void release_cache() const {
#if defined(GAPS_CUDA_KERNELS)
    if (device_.is_cuda()) c10::cuda::CUDACachingAllocator::emptyCache();
#endif
  }
  // Allocated MiB now or at peak since reset_peak(); null off CUDA.
  nlohmann::json allocated_mib(bool peak) const {
#if defined(GAPS_CUDA_KERNELS)
    if (device_.is_cuda()) {
      const auto stats = c10::cuda::CUDACachingAllocator::getDeviceStats(device_.index());
      const auto& all = stats.allocated_bytes[0];
      return static_cast<double>(peak ? all.peak : all.current) / (1024.0 * 1024.0);
    }
#endif
    (void)peak;
    return nullptr;
  }
  std::string name() const {
#if defined(GAPS_CUDA_KERNELS)
    if (device_.is_cuda()) return at::cuda::getDeviceProperties(device_.index())->name;
#endif
    return "cpu";
  }

 private:
  static at::Device with_index(at::Device device) {
#if defined(GAPS_CUDA_KERNELS)
    if (device.is_cuda() && !device.has_index()) return at::Device(at::kCUDA, c10::cuda::current_device());
#endif
    return device;
  }

  at::Device device_;
};

struct Timing {
  double median_ms = 0, min_ms = 0;
  absl::Status status;  // the first failure of f, which stops the timing
};

Timing time_ms(const Device& device, int warmup, int runs, const std::function<absl::Status()>& f) {
  Timing t;
  for (int i = 0; i < warmup && t.status.ok(); ++i) t.status = f();
  device.sync();
  std::vector<double> ms;
  for (int i = 0; i < runs && t.status.ok(); ++i) {
    const auto t0 = std::chrono::steady_clock::now();
    t.status = f();
    device.sync();
    ms.push_back(std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - t0).count());
  }
  if (!t.status.ok() || ms.empty()) return t;
  std::sort(ms.begin(), ms.end());
  t.median_ms = ms[ms.size() / 2];
  t.min_ms = ms.front();
  return t;
}

void emit(const nlohmann::json& j) {
  std::cout << j.dump() << std::endl;
  const std::string path = absl::GetFlag(FLAGS_json);
  if (!path.empty()) std::ofstream(path, std::ios::app) << j.dump() << "\n";
}

bool fail(const std::string& what, const absl::Status& status) {
  std::cerr << "generator_bench: " << what << ": " << status << "\n";
  return false;
}

// Seeded inputs of one size: the pseudo-view's render (padded), its depth control image, the reference view
// of the IP-Adapter (view size, H x W x 3) and an inpainting mask (a band and a corner, as uncovered
// regions at the border of a render look).
struct ViewInputs {
  at::Tensor image, control, reference, mask;
};

ViewInputs view_inputs(const Size& s, int64_t batch, uint64_t seed) {
  at::manual_seed(seed);
  const std::vector<int64_t> pad{0, s.run_width - s.width, 0, s.run_height - s.height};
  ViewInputs in;
  in.image = at::replication_pad2d(at::rand({batch, 3, s.height, s.width}), pad);
  in.control =
      at::replication_pad2d(at::rand({batch, 1, s.height, s.width}).expand({batch, 3, s.height, s.width}), pad);
  in.reference = at::rand({s.height, s.width, 3});
  in.mask = at::zeros({batch, 1, s.run_height, s.run_width});
  in.mask.slice(3, s.run_width * 3 / 4).fill_(1);
  in.mask.slice(2, 0, s.run_height / 4).slice(3, 0, s.run_width / 4).fill_(1);
  return in;
}

struct Bench {
  Device device;
  at::ScalarType dtype;
  std::optional<at::ScalarType> vae_dtype;  // unset: the pipeline's choice
  nlohmann::json common;
  std::vector<Size> sizes;
  std::vector<int64_t> batches;
  Size lora_size;
  std::string weights_dir;
  mutable nlohmann::json phase_peak_mib = nullptr;  // the largest case peak since the last reset of it

  // The allocator's peak since the case began (null off CUDA), kept for the phase's peak.
  nlohmann::json case_peak() const {
    nlohmann::json peak = device.allocated_mib(true);
    if (peak.is_number() && (!phase_peak_mib.is_number() || peak.get<double>() > phase_peak_mib.get<double>())) {
      phase_peak_mib = peak;
    }
    return peak;
  }

  std::string lora_file() const { return weights_dir + "/lora/pytorch_lora_weights.safetensors"; }

  sdxl::Img2ImgParams img2img_params(bool image_prompt, const ViewInputs& in) const {
    sdxl::Img2ImgParams p;
    p.steps = absl::GetFlag(FLAGS_steps);
    p.strength = absl::GetFlag(FLAGS_strength);
    p.guidance_scale = absl::GetFlag(FLAGS_guidance);
    if (image_prompt) {
      p.reference_images.assign(in.image.size(0), in.reference);  // one image prompt per view of the batch
      p.ip_adapter_scales = {absl::GetFlag(FLAGS_ip_scale)};
    }
    return p;
  }

  nlohmann::json line(const std::string& case_name, const Size& s) const {
    nlohmann::json j = common;
    j["case"] = case_name;
    j["size"] = s.name;
    j["run_size"] = {s.run_width, s.run_height};
    return j;
  }

  // Completes a timed case's line with what every timed case reports (its timing, whether its last output
  // is finite, the allocator's peak) and writes it.
  void emit_timed(nlohmann::json j, const Timing& t, const at::Tensor& out) const {
    j["runs"] = absl::GetFlag(FLAGS_runs);
    j["ms"] = t.median_ms;
    j["min_ms"] = t.min_ms;
    j["output_finite"] = out.isfinite().all().item<bool>();
    j["peak_mib"] = case_peak();
    emit(j);
  }

  // One img2img call of a batch of pseudo-views, as the timed and the traced cases make it.
  struct Img2ImgCall {
    ViewInputs in;
    sdxl::Img2ImgParams params;
    sdxl::ControlInput control;
    std::vector<uint64_t> seeds;
    absl::StatusOr<at::Tensor> operator()(sdxl::SdxlPipeline& pipeline) const {
      return pipeline.img2img(in.image, std::vector<std::string>(seeds.size(), kPrompt), params, seeds, control);
    }
  };
  Img2ImgCall img2img_call(const Size& s, int64_t batch, bool image_prompt) const {
    Img2ImgCall call;
    call.in = view_inputs(s, batch, 4);
    call.params = img2img_params(image_prompt, call.in);
    call.control = {call.in.control, {absl::GetFlag(FLAGS_control_scale)}};
    call.seeds.resize(batch);
    std::iota(call.seeds.begin(), call.seeds.end(), uint64_t{1234});
    return call;
  }

  // Batches of pseudo-views through the pipeline at every size and batch size (--batches): img2img with the
  // ControlNet, optionally the image prompt.
  bool time_img2img(sdxl::SdxlPipeline& pipeline, const std::string& case_name, bool image_prompt) const {
    for (const Size& s : sizes) {
      for (const int64_t batch : batches) {
        const Img2ImgCall call = img2img_call(s, batch, image_prompt);
        const sdxl::Img2ImgParams& params = call.params;
        at::Tensor out;
        device.reset_peak();
        const Timing t = time_ms(device, absl::GetFlag(FLAGS_warmup), absl::GetFlag(FLAGS_runs), [&]() -> absl::Status {
          auto result = call(pipeline);
          if (!result.ok()) return result.status();
          out = *result;
          return absl::OkStatus();
        });
        if (!t.status.ok()) return fail(absl::StrCat(case_name, " at ", s.name, " batch ", batch), t.status);
        nlohmann::json j = line(case_name, s);
        j["batch"] = batch;
        j["steps"] = params.steps;
        j["strength"] = params.strength;
        j["unet_steps"] = static_cast<int>(params.steps * params.strength);
        j["guidance"] = params.guidance_scale;
        j["controlnet_scale"] = absl::GetFlag(FLAGS_control_scale);
        j["ip_adapter_scale"] = image_prompt ? nlohmann::json(absl::GetFlag(FLAGS_ip_scale)) : nlohmann::json(nullptr);
        j["lora"] = pipeline.lora() != nullptr;
        j["cuda_graphs"] = absl::GetFlag(FLAGS_cuda_graphs);
        j["ms_per_view"] = t.median_ms / static_cast<double>(batch);
        emit_timed(j, t, out);
      }
    }
    return case_name != "img2img_controlnet_ip_lora" || trace_img2img(pipeline, image_prompt);
  }

  // One call of the last size and batch under the profiler (--img2img_trace), apart from the timed runs, whose
  // time the profiler would inflate.
  bool trace_img2img(sdxl::SdxlPipeline& pipeline, bool image_prompt) const {
    const std::string trace = absl::GetFlag(FLAGS_img2img_trace);
    if (trace.empty()) return true;
    const int64_t batch = batches.back();
    const Img2ImgCall call = img2img_call(sizes.back(), batch, image_prompt);
    gaps::bench::KinetoTrace profiler(device.device().is_cuda());
    device.sync();
    profiler.start();
    auto result = call(pipeline);
    device.sync();
    profiler.stop_and_save(trace);
    if (!result.ok()) return fail("img2img (traced)", result.status());
    std::cerr << "generator_bench: one img2img call of batch " << batch << " traced into " << trace << "\n";
    return true;
  }

  sdxl::PipelineOptions pipeline_options(bool ip_adapter) const {
    sdxl::PipelineOptions o{
        dtype, device.device(), "", absl::GetFlag(FLAGS_cuda_graphs), "", weights_dir + "/controlnet"};
    if (ip_adapter) {
      o.ip_adapter = weights_dir + "/ip_adapter/ip-adapter_sdxl_vit-h.safetensors";
      o.image_encoder = weights_dir + "/ip_adapter/image_encoder";
    }
    o.vae_dtype = vae_dtype;
    o.channels_last = absl::GetFlag(FLAGS_channels_last);
    return o;
  }

  // A few LoRA training steps under the profiler (--lora_trace), apart from the timed run, whose time the
  // profiler would inflate.
  bool trace_lora_training(sdxl::SdxlPipeline& pipeline, const ViewInputs& in, const sdxl::ControlInput& control,
                           const sdxl::LoraConfig& config) const {
    const std::string trace = absl::GetFlag(FLAGS_lora_trace);
    if (trace.empty()) return true;
    sdxl::LoraTrainingOptions options;
    options.steps = absl::GetFlag(FLAGS_lora_trace_steps);
    gaps::bench::KinetoTrace profiler(device.device().is_cuda());
    device.sync();
    profiler.start();
    auto trained = pipeline.train_lora(in.image, {kPrompt}, control, config, options);
    device.sync();
    profiler.stop_and_save(trace);
    if (!trained.ok()) return fail("LoRA training (traced)", trained.status());
    std::cerr << "generator_bench: " << options.steps << " LoRA training steps traced into " << trace << "\n";
    return true;
  }

  // (c) LoRA training on the ControlNet pipeline, then ControlNet + LoRA img2img (LoRA training and the
  // IP-Adapter do not go together: the backend refuses that combination).
  bool lora_phase(const std::string& sdxl_dir) const {
    device.reset_peak();
    auto pipeline = sdxl::SdxlPipeline::load(sdxl_dir, pipeline_options(false));
    if (!pipeline.ok()) return fail("loading SDXL + ControlNet", pipeline.status());
    const int views = absl::GetFlag(FLAGS_lora_views);
    const ViewInputs in = view_inputs(lora_size, views, 5);
    const sdxl::ControlInput control{in.control, {1.0}};
    sdxl::LoraConfig config;
    config.rank = absl::GetFlag(FLAGS_lora_rank);
    config.alpha = static_cast<double>(config.rank);
    sdxl::LoraTrainingOptions options;  // the backend's defaults: learning rate 1e-4, Adam
    options.steps = 2;
    if (auto warm = (*pipeline)->train_lora(in.image, {kPrompt}, control, config, options); !warm.ok()) {
      return fail("LoRA training (warm-up)", warm.status());
    }
    options.steps = absl::GetFlag(FLAGS_lora_steps);
    // Eager steps and, on CUDA, the captured step replayed (the backend's lora_cuda_graph), one after the other.
    for (const bool cuda_graph : {false, true}) {
      if (cuda_graph && !device.device().is_cuda()) continue;
      options.cuda_graph = cuda_graph;
      std::vector<double> losses;
      device.reset_peak();
      const Timing t = time_ms(device, 0, 1, [&]() -> absl::Status {
        auto trained = (*pipeline)->train_lora(in.image, {kPrompt}, control, config, options);
        if (!trained.ok()) return trained.status();
        losses = *trained;
        return absl::OkStatus();
      });
      if (!t.status.ok()) return fail(cuda_graph ? "LoRA training (CUDA graph)" : "LoRA training", t.status);
      nlohmann::json j = line("lora_training", lora_size);
      j["views"] = views;
      j["steps"] = options.steps;
      j["rank"] = config.rank;
      j["controlnet"] = true;
      j["cuda_graph"] = cuda_graph;
      j["ms"] = t.median_ms;
      j["ms_per_step"] = t.median_ms / static_cast<double>(options.steps);
      j["first_loss"] = losses.front();
      j["last_loss"] = losses.back();
      j["peak_mib"] = case_peak();
      emit(j);
    }
    if (!trace_lora_training(**pipeline, in, control, config)) return false;
    if (absl::Status s = (*pipeline)->load_lora(lora_file()); !s.ok()) return fail("loading the LoRA", s);
    return time_img2img(**pipeline, "img2img_controlnet_lora", false);
  }

  bool time_inpaint(sdxl::InpaintPipeline& pipeline) const {
    sdxl::InpaintParams params;
    params.steps = absl::GetFlag(FLAGS_inpaint_steps);
    params.guidance_scale = absl::GetFlag(FLAGS_inpaint_guidance);
    for (const Size& s : sizes) {
      const ViewInputs in = view_inputs(s, 1, 6);
      at::Tensor out;
      device.reset_peak();
      const Timing t = time_ms(device, absl::GetFlag(FLAGS_warmup), absl::GetFlag(FLAGS_runs), [&]() -> absl::Status {
        auto result = pipeline.inpaint(in.image, in.mask, {kPrompt}, params, {1234});
        if (!result.ok()) return result.status();
        out = *result;
        return absl::OkStatus();
      });
      if (!t.status.ok()) return fail("inpaint at " + s.name, t.status);
      nlohmann::json j = line("inpaint", s);
      j["steps"] = params.steps;
      j["strength"] = params.strength;
      j["guidance"] = params.guidance_scale;
      j["masked_fraction"] = in.mask.mean().item<double>();
      emit_timed(j, t, out);
    }
    return true;
  }

  bool time_depth(const depth::DepthAnything& model) const {
    const Size& s = sizes.front();
    at::manual_seed(7);
    const at::Tensor image = at::rand({s.height, s.width, 3});
    at::Tensor out;
    device.reset_peak();
    const Timing t = time_ms(device, absl::GetFlag(FLAGS_warmup), absl::GetFlag(FLAGS_runs), [&]() -> absl::Status {
      auto depth = model.estimate_depth(image);
      if (!depth.ok()) return depth.status();
      out = *depth;
      return absl::OkStatus();
    });
    if (!t.status.ok()) return fail("Depth-Anything", t.status);
    nlohmann::json j = line("depth_anything", s);
    emit_timed(j, t, out);
    return true;
  }

  // (a) with the IP-Adapter, (b) and (d): everything the worker holds, loaded together.
  bool worker_phase(const std::string& sdxl_dir) const {
    device.release_cache();
    device.reset_peak();
    const auto t0 = std::chrono::steady_clock::now();
    auto pipeline = sdxl::SdxlPipeline::load(sdxl_dir, pipeline_options(true));
    if (!pipeline.ok()) return fail("loading SDXL + ControlNet + IP-Adapter", pipeline.status());
    auto inpaint = sdxl::InpaintPipeline::load(
        weights_dir + "/sd2_inpaint",
        sdxl::InpaintPipelineOptions{dtype, device.device(), absl::GetFlag(FLAGS_inpaint_scheduler), ""});
    if (!inpaint.ok()) return fail("loading SD2 inpainting", inpaint.status());
    auto depth = depth::DepthAnything::load(weights_dir + "/depth_anything",
                                            at::TensorOptions().dtype(dtype).device(device.device()));
    if (!depth.ok()) return fail("loading Depth-Anything", depth.status());
    device.sync();
    nlohmann::json load = common;
    load["case"] = "load_all";
    load["components"] = {"sdxl", "controlnet", "ip_adapter", "image_encoder", "sd2_inpaint", "depth_anything"};
    load["seconds"] = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
    load["allocated_mib"] = device.allocated_mib(false);
    emit(load);
    phase_peak_mib = load["allocated_mib"];
    if (!time_img2img(**pipeline, "img2img_controlnet_ip", true)) return false;
    if (absl::Status s = (*pipeline)->load_lora(lora_file()); !s.ok()) return fail("loading the LoRA", s);
    if (!time_img2img(**pipeline, "img2img_controlnet_ip_lora", true)) return false;
    if (!time_inpaint(**inpaint)) return false;
    if (!time_depth(*depth)) return false;
    nlohmann::json peak = common;
    peak["case"] = "worker_peak";
    peak["components"] = {"sdxl", "controlnet", "ip_adapter", "image_encoder", "lora", "sd2_inpaint", "depth_anything"};
    peak["sizes"] = absl::GetFlag(FLAGS_sizes);
    peak["loaded_mib"] = load["allocated_mib"];
    peak["peak_mib"] = phase_peak_mib;  // each case resets the allocator's peak: the largest of theirs
    emit(peak);
    return true;
  }
};

}  // namespace

int main(int argc, char** argv) {
  absl::ParseCommandLine(argc, argv);
  // cuDNN's autotuner picks each convolution's algorithm by timing the candidates at the first call of a shape.
  at::globalContext().setBenchmarkCuDNN(absl::GetFlag(FLAGS_cudnn_benchmark));
  const std::string sdxl_dir = absl::GetFlag(FLAGS_sdxl_dir);
  if (!gaps::bench::ensure_random_sdxl(sdxl_dir, absl::GetFlag(FLAGS_write_model), absl::GetFlag(FLAGS_configs_from),
                                       absl::GetFlag(FLAGS_weights_seed), "generator_bench")) {
    return 1;
  }
  if (absl::GetFlag(FLAGS_write_only)) return 0;

  at::Device device(at::kCPU);
  try {
    device = at::Device(absl::GetFlag(FLAGS_device));
  } catch (const std::exception&) {
    std::cerr << "generator_bench: --device " << absl::GetFlag(FLAGS_device)
              << " is not a device (cpu, cuda, cuda:N)\n";
    return 2;
  }
  if (device.is_cuda() && !at::hasCUDA()) {
    std::cerr << "generator_bench: no CUDA device (or a build without CUDA); the full-size models (fp16, about 13 GB "
                 "of weights) run on a GPU. --device cpu --dtype float32 runs the tiny models on the CPU.\n";
    return 2;
  }
  if (device.is_cuda() && !device.has_index()) device = at::Device(at::kCUDA, 0);
  const auto scalar_type = [](const std::string& name) {
    return name == "float16"    ? std::optional(at::kHalf)
           : name == "bfloat16" ? std::optional(at::kBFloat16)
           : name == "float32"  ? std::optional(at::kFloat)
                                : std::nullopt;
  };
  const std::string dtype_name = absl::GetFlag(FLAGS_dtype);
  const std::optional<at::ScalarType> dtype = scalar_type(dtype_name);
  if (!dtype || (device.is_cpu() && *dtype != at::kFloat)) {
    std::cerr << "generator_bench: --dtype must be float16, bfloat16 or float32 (float32 on the CPU)\n";
    return 2;
  }
  if (device.is_cuda()) at::empty({1}, at::TensorOptions().device(device));  // starts the allocator's statistics

  const auto factor_folder = sdxl::ModelFolder::open(sdxl_dir);
  auto vae = factor_folder.ok() ? factor_folder->read_json("vae") : factor_folder.status();
  if (!vae.ok()) {
    fail("the SDXL folder's VAE config", vae.status());
    return 1;
  }
  const int64_t factor = int64_t{1} << ((*vae)["block_out_channels"].size() - 1);
  std::vector<Size> sizes;
  const std::vector<std::string> size_items = absl::StrSplit(absl::GetFlag(FLAGS_sizes), ',');
  for (const std::string& item : size_items) {
    const std::optional<Size> s = parse_size(item, factor);
    if (!s) {
      std::cerr << "generator_bench: --sizes entry '" << item << "' is not WxH\n";
      return 2;
    }
    sizes.push_back(*s);
  }
  std::vector<int64_t> batches;
  for (const absl::string_view item : absl::StrSplit(absl::GetFlag(FLAGS_batches), ',')) {
    int64_t batch = 0;
    if (!absl::SimpleAtoi(item, &batch) || batch < 1) {
      std::cerr << "generator_bench: --batches entry '" << item << "' is not a positive integer\n";
      return 2;
    }
    batches.push_back(batch);
  }
  const std::optional<Size> lora_size = parse_size(absl::GetFlag(FLAGS_lora_size), factor);
  if (sizes.empty() || !lora_size) {
    std::cerr << "generator_bench: --sizes and --lora_size take WxH\n";
    return 2;
  }

  const Device dev(device);
  nlohmann::json common;
  common["bench"] = "generator";
  common["impl"] = "gaps-libtorch";
  common["cudnn_benchmark"] = absl::GetFlag(FLAGS_cudnn_benchmark);
  common["device"] = dev.name();
  common["torch"] = TORCH_VERSION;
  common["dtype"] = dtype_name;
  const std::string vae_dtype_name = absl::GetFlag(FLAGS_vae_dtype);
  const std::optional<at::ScalarType> vae_dtype = scalar_type(vae_dtype_name);
  if (!vae_dtype_name.empty() && (!vae_dtype || (device.is_cpu() && *vae_dtype != at::kFloat))) {
    std::cerr << "generator_bench: --vae_dtype must be \"\", float16, bfloat16 or float32 (float32 on the CPU)\n";
    return 2;
  }
  common["vae_dtype"] = vae_dtype_name.empty() ? "float32 (force_upcast)" : vae_dtype_name;
  common["channels_last"] = absl::GetFlag(FLAGS_channels_last);
  common["commit"] = absl::GetFlag(FLAGS_commit);
  const Bench bench{dev, *dtype, vae_dtype, common, sizes, batches, *lora_size, absl::GetFlag(FLAGS_weights_dir)};
  const std::vector<std::string> phases = absl::StrSplit(absl::GetFlag(FLAGS_phases), ',');
  const auto asked = [&](const char* phase) { return std::find(phases.begin(), phases.end(), phase) != phases.end(); };
  for (const std::string& phase : phases) {
    if (phase != "lora" && phase != "worker") {
      std::cerr << "generator_bench: --phases takes lora, worker or both (lora,worker), not '" << phase << "'\n";
      return 2;
    }
  }
  if (asked("lora") && !bench.lora_phase(sdxl_dir)) return 1;
  if (asked("worker") && !bench.worker_phase(sdxl_dir)) return 1;
  return 0;
}

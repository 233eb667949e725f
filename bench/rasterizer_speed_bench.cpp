// Rasterizer speed: forward and forward+backward milliseconds per render() call (projection, SH colour,
// tile binning, compositing, and their backward) on random Gaussians in front of a camera with f = 800,
// SH degree 3, every Gaussian in the view: the setup of the Inria rasterizer figures in
// shared/gpu/README.md. Also the split between the rasterizer's stages (backend calls, synchronised
// one by one). CUDA for every case, CPU for the smallest. One JSON line per case and device.
// With --dump_dir, each case's Gaussians (standard 3DGS PLY) and camera (JSON) are written there, so that
// bench/rasterizer_compare.py times gsplat on exactly the same input in the same run.
//   rasterizer_speed_bench [--runs 20] [--cpu_runs 3] [--json results.jsonl] [--dump_dir DIR]
#include <algorithm>
#include <chrono>
#include <cmath>
#include <filesystem>
#include <fstream>
#include <functional>
#include <iostream>
#include <string>
#include <vector>

#include <ATen/ATen.h>
#include <ATen/Parallel.h>
#include <c10/core/GradMode.h>
#include <torch/headeronly/version.h>
#include <nlohmann/json.hpp>
#include "absl/flags/flag.h"
#include "absl/flags/parse.h"
#include "gs_trainer/model/gaussians.h"
#include "gs_trainer/model/render.h"
#include "gs_trainer/raster/rasterize_backend.h"

#if defined(GAPS_CUDA_KERNELS)
#include <ATen/cuda/CUDAContext.h>
#include <c10/cuda/CUDACachingAllocator.h>
#include <cuda_runtime.h>
#endif

ABSL_FLAG(int, runs, 20, "timed CUDA runs per case (the median is reported)");
ABSL_FLAG(int, cpu_runs, 3, "timed CPU runs for the smallest case (0: skip the CPU)");
ABSL_FLAG(std::string, json, "", "also append the JSON lines to this file");
ABSL_FLAG(std::string, dump_dir, "", "write each case's Gaussians (PLY) and camera (JSON) to this folder");

namespace {

struct Case {
  const char* name;
  int64_t n;
  int width, height;
};

void sync(const at::Device& device) {
#if defined(GAPS_CUDA_KERNELS)
  if (device.is_cuda()) {
    const cudaError_t err = cudaDeviceSynchronize();
    TORCH_CHECK(err == cudaSuccess, "cudaDeviceSynchronize: ", cudaGetErrorString(err));
  }
#else
  (void)device;
#endif
}

// Median milliseconds of `runs` calls of f, each followed by a device synchronisation, after `warmup`.
double median_ms(const at::Device& device, int warmup, int runs, const std::function<void()>& f) {
  for (int i = 0; i < warmup; ++i) f();
  sync(device);
  std::vector<double> ms;
  for (int i = 0; i < runs; ++i) {
    const auto t0 = std::chrono::steady_clock::now();
    f();
    sync(device);
    ms.push_back(std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - t0).count());
  }
  std::sort(ms.begin(), ms.end());
  return ms[ms.size() / 2];
}

gaps::Camera make_camera(int width, int height) {
  gaps::Camera c;
  c.width = width;
  c.height = height;
  c.fx = c.fy = 800.0;
  c.cx = 0.5 * width;
  c.cy = 0.5 * height;
  return c;  // identity pose: looking down +z from the origin
}

// Means 2 to 6 units in front of the camera, uniformly over the image; scales log-uniform in
// [0.005, 0.02] (1 to 8 px standard deviations at these depths); random rotations; opacities
// sigmoid(U(-2, 2)); SH degree 3.
gaps::GaussianModel make_model(int64_t n, const gaps::Camera& c, uint64_t seed) {
  at::manual_seed(seed);
  gaps::GaussianModel m;
  const at::Tensor z = at::rand({n}) * 4.0 + 2.0;
  const at::Tensor x = (at::rand({n}) * c.width - c.cx) / c.fx * z;
  const at::Tensor y = (at::rand({n}) * c.height - c.cy) / c.fy * z;
  m.means = at::stack({x, y, z}, 1);
  m.log_scales = at::rand({n, 3}) * std::log(4.0) + std::log(0.005);
  m.quats = at::randn({n, 4});
  m.opacity_logits = at::rand({n}) * 4.0 - 2.0;
  m.sh_dc = at::randn({n, 1, 3}) * 0.5;
  m.sh_rest = at::randn({n, 15, 3}) * 0.1;
  m.max_sh_degree = 3;
  m.sh_degree = 3;
  return m;
}

void reset_peak_memory(const at::Device& device) {
#if defined(GAPS_CUDA_KERNELS)
  if (device.is_cuda()) c10::cuda::CUDACachingAllocator::resetPeakStats(device.index());
#else
  (void)device;
#endif
}

// Peak bytes held by tensors on the device since the last reset (the caching allocator's own figure, as
// torch.cuda.max_memory_allocated reports it); -1 on the CPU.
double peak_memory_mib(const at::Device& device) {
#if defined(GAPS_CUDA_KERNELS)
  if (device.is_cuda()) {
    const auto stats = c10::cuda::CUDACachingAllocator::getDeviceStats(device.index());
    return static_cast<double>(stats.allocated_bytes[0].peak) / (1024.0 * 1024.0);
  }
#else
  (void)device;
#endif
  return -1.0;
}

void dump_case(const Case& cs, const gaps::GaussianModel& model, const gaps::Camera& camera, const std::string& dir) {
  std::filesystem::create_directories(dir);
  const std::string stem = dir + "/" + cs.name;
  const absl::Status saved = gaps::save_gaussians_ply(model, stem + ".ply");
  TORCH_CHECK(saved.ok(), "writing ", stem, ".ply: ", saved.message());
  nlohmann::json j = {{"width", camera.width}, {"height", camera.height}, {"fx", camera.fx},      {"fy", camera.fy},
                      {"cx", camera.cx},       {"cy", camera.cy},         {"viewmat", "identity"}};
  std::ofstream(stem + ".json") << j.dump(1) << "\n";
}

// Our colour image of the case (H x W x 3 float32, raw), so that rasterizer_compare.py can check that the reference
// renderers were handed the same scene (their images must agree with it).
void dump_render(const Case& cs, const gaps::GaussianModel& model, const gaps::Camera& camera) {
  c10::NoGradGuard no_grad;
  const at::Tensor rgb = gaps::render(model, camera).rgb.contiguous().cpu();
  std::ofstream(absl::GetFlag(FLAGS_dump_dir) + "/" + cs.name + "_rgb.f32", std::ios::binary)
      .write(static_cast<const char*>(rgb.data_ptr()), static_cast<std::streamsize>(rgb.nbytes()));
}

nlohmann::json time_case(const Case& cs, const at::Device& device, int runs) {
  const gaps::Camera camera = make_camera(cs.width, cs.height);
  if (!absl::GetFlag(FLAGS_dump_dir).empty() && device.is_cuda())
    dump_case(cs, make_model(cs.n, camera, 1), camera, absl::GetFlag(FLAGS_dump_dir));
  gaps::GaussianModel model = make_model(cs.n, camera, 1).to(device);
  if (!absl::GetFlag(FLAGS_dump_dir).empty() && device.is_cuda()) dump_render(cs, model, camera);
  for (at::Tensor* p : model.parameters()) p->requires_grad_(true);
  const auto opts = model.means.options();
  at::manual_seed(2);
  const at::Tensor w_rgb = at::randn({cs.height, cs.width, 3}, opts);
  const at::Tensor w_alpha = at::randn({cs.height, cs.width}, opts);
  const int warmup = device.is_cuda() ? 3 : 1;

  nlohmann::json j;
  j["case"] = cs.name;
  j["device"] = device.is_cuda() ? "cuda" : "cpu";
  j["gaussians"] = cs.n;
  j["width"] = cs.width;
  j["height"] = cs.height;
  j["runs"] = runs;
  {
    c10::NoGradGuard no_grad;
    j["forward_ms"] = median_ms(device, warmup, runs, [&] { gaps::render(model, camera); });
  }
  reset_peak_memory(device);
  j["forward_backward_ms"] = median_ms(device, warmup, runs, [&] {
    for (at::Tensor* p : model.parameters()) p->mutable_grad().reset();
    const auto out = gaps::render(model, camera);
    ((out.rgb * w_rgb).sum() + (out.alpha * w_alpha).sum()).backward();
  });
  j["forward_backward_peak_mib"] = peak_memory_mib(device);

  // Stage split through the backend (what the autograd functions call), colours precomputed.
  namespace be = gaps::backend;
  c10::NoGradGuard no_grad;
  const gaps::raster::Intrinsics K{camera.fx, camera.fy, camera.cx, camera.cy, camera.width, camera.height};
  const at::Tensor means = model.means.detach(), quats = model.quats.detach();
  const at::Tensor scales = model.scales().detach(), opacities = model.opacities().detach();
  const at::Tensor viewmat = camera.viewmat().to(opts);
  const at::Tensor features = at::rand({cs.n, 4}, opts);
  const bool cuda = device.is_cuda();
  auto project = [&] {
#if defined(GAPS_CUDA_KERNELS)
    if (cuda) return be::project_forward_cuda(means, quats, scales, viewmat, K);
#endif
    return be::project_forward_cpu(means, quats, scales, viewmat, K);
  };
  const be::Projection p = project();
  auto bin = [&] {
#if defined(GAPS_CUDA_KERNELS)
    if (cuda) return be::bin_tiles_cuda(p.means2d, p.conics, opacities, p.radii, p.depths, cs.width, cs.height);
#endif
    return be::bin_tiles_cpu(p.means2d, p.conics, opacities, p.radii, p.depths, cs.width, cs.height);
  };
  const be::TileBins bins = bin();
  auto composite = [&] {
#if defined(GAPS_CUDA_KERNELS)
    if (cuda) return be::rasterize_forward_cuda(bins, p.means2d, p.conics, opacities, features, cs.width, cs.height);
#endif
    return be::rasterize_forward_cpu(bins, p.means2d, p.conics, opacities, features, cs.width, cs.height);
  };
  const be::RasterOutput fwd = composite();
  const at::Tensor g_feat = at::randn({cs.height, cs.width, 4}, opts), g_alpha = at::randn({cs.height, cs.width}, opts);
  auto composite_backward = [&] {
#if defined(GAPS_CUDA_KERNELS)
    if (cuda) return be::rasterize_backward_cuda(bins, p.means2d, p.conics, opacities, features, fwd, g_feat, g_alpha);
#endif
    return be::rasterize_backward_cpu(bins, p.means2d, p.conics, opacities, features, fwd, g_feat, g_alpha);
  };
  const be::RasterGrads rg = composite_backward();
  auto project_backward = [&] {
#if defined(GAPS_CUDA_KERNELS)
    if (cuda) return be::project_backward_cuda(means, quats, scales, viewmat, K, p.radii, rg.means2d, rg.conics);
#endif
    return be::project_backward_cpu(means, quats, scales, viewmat, K, p.radii, rg.means2d, rg.conics);
  };
  j["visible"] = (p.radii > 0).sum().item<int64_t>();
  j["tile_entries"] = bins.gaussian_ids.numel();
  j["stages_ms"] = {
      {"project", median_ms(device, warmup, runs, [&] { project(); })},
      {"bin_tiles", median_ms(device, warmup, runs, [&] { bin(); })},
      {"composite", median_ms(device, warmup, runs, [&] { composite(); })},
      {"composite_backward", median_ms(device, warmup, runs, [&] { composite_backward(); })},
      {"project_backward", median_ms(device, warmup, runs, [&] { project_backward(); })},
  };
  return j;
}

}  // namespace

int main(int argc, char** argv) {
  absl::ParseCommandLine(argc, argv);
  const std::vector<Case> cases = {
      {"100k_504x378", 100000, 504, 378}, {"300k_504x378", 300000, 504, 378}, {"1M_1000x1000", 1000000, 1000, 1000}};
  nlohmann::json common;
  common["torch"] = TORCH_VERSION;
  common["cpu_threads"] = at::get_num_threads();
#if defined(GAPS_CUDA_KERNELS)
  const bool has_cuda = at::hasCUDA();
  if (has_cuda) common["gpu"] = at::cuda::getDeviceProperties(0)->name;
#else
  const bool has_cuda = false;
#endif
  std::vector<nlohmann::json> lines;
  if (has_cuda) {
    for (const Case& cs : cases) lines.push_back(time_case(cs, at::Device(at::kCUDA, 0), absl::GetFlag(FLAGS_runs)));
  } else {
    std::cerr << "no CUDA device (or built without the CUDA kernels): timing the CPU only\n";
  }
  if (absl::GetFlag(FLAGS_cpu_runs) > 0) lines.push_back(time_case(cases[0], at::kCPU, absl::GetFlag(FLAGS_cpu_runs)));

  std::ofstream file;
  if (!absl::GetFlag(FLAGS_json).empty()) file.open(absl::GetFlag(FLAGS_json), std::ios::app);
  for (nlohmann::json& j : lines) {
    j.update(common);
    std::cout << j.dump() << std::endl;
    if (file) file << j.dump() << "\n";
  }
  return 0;
}

#include "gs_trainer/run/stats.h"

#include <sys/resource.h>

#include <chrono>

#include <c10/core/CachingDeviceAllocator.h>
#include <nlohmann/json.hpp>

namespace gaps {
namespace {

constexpr size_t kAggregate = static_cast<size_t>(c10::CachingAllocator::StatType::AGGREGATE);

nlohmann::json optional_json(const std::optional<double>& v) {
  return v ? nlohmann::json(*v) : nlohmann::json(nullptr);
}

c10::DeviceIndex cuda_index(const at::Device& device) { return device.has_index() ? device.index() : 0; }

template <typename F>
auto timed(double& seconds, F&& f) {
  const auto start = std::chrono::steady_clock::now();
  auto result = f();
  seconds += std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
  return result;
}

}  // namespace

void to_json(nlohmann::json& j, const CurvePoint& p) {
  j = {{"iteration", p.iteration}, {"train_seconds", p.train_seconds},        {"psnr", p.metrics.psnr},
       {"ssim", p.metrics.ssim},   {"lpips", optional_json(p.metrics.lpips)}, {"num_gaussians", p.num_gaussians}};
}

void from_json(const nlohmann::json& j, CurvePoint& p) {
  p.iteration = j.at("iteration");
  p.train_seconds = j.at("train_seconds");
  p.metrics.psnr = j.at("psnr");
  p.metrics.ssim = j.at("ssim");
  p.metrics.lpips = j.at("lpips").is_null() ? std::nullopt : std::optional<double>(j.at("lpips").get<double>());
  p.num_gaussians = j.at("num_gaussians");
}

void to_json(nlohmann::json& j, const PeakMemory& m) {
  j = {{"kind", m.kind}, {"bytes", m.bytes}};
  if (m.reserved_bytes) j["reserved_bytes"] = *m.reserved_bytes;
}

PeakMemoryMeter::PeakMemoryMeter(const at::Device& device) : device_(device) {
  if (device_.is_cuda()) c10::getDeviceAllocator(c10::DeviceType::CUDA)->resetPeakStats(cuda_index(device_));
}

PeakMemory PeakMemoryMeter::read() const {
  PeakMemory m;
  if (device_.is_cuda()) {
    const auto stats = c10::getDeviceAllocator(c10::DeviceType::CUDA)->getDeviceStats(cuda_index(device_));
    m.kind = "cuda_allocator";
    m.bytes = stats.allocated_bytes[kAggregate].peak;
    m.reserved_bytes = stats.reserved_bytes[kAggregate].peak;
    return m;
  }
  rusage usage{};
  getrusage(RUSAGE_SELF, &usage);
  m.kind = "cpu_rss";
  m.bytes = static_cast<int64_t>(usage.ru_maxrss) * 1024;  // Linux reports kilobytes
  return m;
}

absl::Status TimedGenerator::adapt(const std::vector<ReferenceView>& views,
                                   const std::optional<SceneAdaptation>& adaptation) {
  return timed(seconds_, [&] { return inner_->adapt(views, adaptation); });
}

absl::StatusOr<std::vector<at::Tensor>> TimedGenerator::generate(const std::vector<GenerationRequest>& requests) {
  return timed(seconds_, [&] { return inner_->generate(requests); });
}

}  // namespace gaps
